"""What every task's configuration shares: strict YAML models, dotted overrides, tracking, flattening for MLflow."""

from __future__ import annotations

from pathlib import Path

import yaml
from pydantic import BaseModel, ConfigDict


class ConfigError(ValueError):
    """A config file or override that cannot be read; the message says what was expected and what came."""


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
    path = Path(path)
    if not path.is_file():
        raise ConfigError(f"config file {str(path)!r} not found")
    try:
        raw = yaml.safe_load(path.read_text()) or {}
    except yaml.YAMLError as exc:
        raise ConfigError(f"{path}: not valid YAML: {exc}") from None
    if not isinstance(raw, dict):
        raise ConfigError(f"{path}: expected a mapping of sections (train:, data:, ...), got {type(raw).__name__}")
    for item in overrides or []:
        key, sep, value = item.partition("=")
        if not sep or not key:
            raise ConfigError(f"override {item!r}: expected dotted.key=value (e.g. train.max_epochs=2)")
        node = raw
        *parents, leaf = key.split(".")
        for k, p in enumerate(parents):
            node = node.setdefault(p, {})
            if not isinstance(node, dict):
                where = ".".join(parents[: k + 1])
                raise ConfigError(f"override {item!r}: {where} is a value ({node!r}), not a section with keys")
        try:
            node[leaf] = yaml.safe_load(value)
        except yaml.YAMLError as exc:
            raise ConfigError(f"override {item!r}: its value is not valid YAML: {exc}") from None
    return raw
