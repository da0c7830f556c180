"""What every task's configuration shares: strict YAML models, dotted overrides, tracking, flattening for MLflow."""

from __future__ import annotations

from pathlib import Path

import yaml
from pydantic import BaseModel, ConfigDict


class Strict(BaseModel):
    """A config section that rejects unknown keys (a typo in a YAML file is an error, not a silent default)."""

    model_config = ConfigDict(extra="forbid")


class TrackingConfig(Strict):
    experiment: str = "i2s"
    registered_model: str | None = None  # defaults to the experiment name of the config


def flatten(d: dict, prefix: str = "") -> dict[str, object]:
    """Dotted keys → values of a nested (dumped) config, e.g. ``{"train.lr": 0.001}``."""
    out: dict[str, object] = {}
    for k, v in d.items():
        key = f"{prefix}{k}"
        if isinstance(v, dict):
            out.update(flatten(v, key + "."))
        else:
            out[key] = v
    return out


def read_yaml(path: str | Path, overrides: list[str] | None = None) -> dict:
    """A YAML config as a dict; ``overrides`` are ``dotted.key=yaml_value`` strings (e.g. ``train.max_epochs=2``)."""
    raw = yaml.safe_load(Path(path).read_text())
    for item in overrides or []:
        key, _, value = item.partition("=")
        node = raw
        *parents, leaf = key.split(".")
        for p in parents:
            node = node.setdefault(p, {})
        node[leaf] = yaml.safe_load(value)
    return raw
