"""Loads every model under the models directory through its manifest and refuses mismatches.

A model is served only if its sha256 and its input/output names and shapes match ``manifest.json``;
a mismatching model is logged and skipped while the others are served. Per name, the highest
version wins (compared by its numeric parts: 1.10.0 > 1.9.0, 2026.11.22-0730 > 2026.11.21-2359).
"""

from __future__ import annotations

import logging
import re
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import onnxruntime as ort

from service.core.manifest import Manifest, read_manifest, sha256_file

log = logging.getLogger(__name__)
POSE_TASKS = ("imu_pose", "imu_pose_velocity", "flex_pose")


class ModelMismatch(ValueError):
    """The ONNX file does not match its manifest."""


@dataclass
class LoadedModel:
    manifest: Manifest
    session: ort.InferenceSession
    path: Path
    source: str = ""  # the directory, or the registry URI and version it was fetched from

    def run(self, x: np.ndarray) -> np.ndarray:
        """The manifest's single input (e.g. IMU windows ``(B, 128, 6)``) float32 → its single output."""
        return self.session.run(None, {self.manifest.inputs[0].name: x})[0]


def _check_shapes(manifest: Manifest, session: ort.InferenceSession) -> None:
    for kind, declared, actual in (
        ("input", manifest.inputs, session.get_inputs()),
        ("output", manifest.outputs, session.get_outputs()),
    ):
        names = [t.name for t in declared]
        if names != [a.name for a in actual]:
            raise ModelMismatch(f"{kind} names: manifest says {names}, model has {[a.name for a in actual]}")
        for spec, arg in zip(declared, actual, strict=True):
            fixed_declared = [d for d in spec.shape if isinstance(d, int)]
            fixed_actual = [d for d in arg.shape if isinstance(d, int)]
            if fixed_declared != fixed_actual:
                raise ModelMismatch(f"{kind} {spec.name}: manifest shape {spec.shape}, model shape {arg.shape}")


def load_model(model_dir: Path, threads: int) -> LoadedModel:
    manifest = read_manifest(model_dir / "manifest.json")
    onnx_path = model_dir / "model.onnx"
    digest = sha256_file(onnx_path)
    if digest != manifest.sha256:
        raise ModelMismatch(f"sha256 of {onnx_path} is {digest}, manifest says {manifest.sha256}")
    options = ort.SessionOptions()
    options.intra_op_num_threads = threads
    options.inter_op_num_threads = 1
    # No busy-waiting: the event loop, other sessions and clients share the cores (benchmarks/bench_service.py:
    # single-window p50 16.9 -> 11.8 ms, 50-stream result p99 593 -> 110 ms on 2 cores).
    options.add_session_config_entry("session.intra_op.allow_spinning", "0")
    session = ort.InferenceSession(str(onnx_path), options, providers=["CPUExecutionProvider"])
    _check_shapes(manifest, session)
    return LoadedModel(manifest, session, model_dir, str(model_dir))


def version_key(version: str) -> tuple[int, ...]:
    return tuple(int(part) for part in re.findall(r"\d+", version))


def newest_version_dir(root: Path, name: str) -> Path | None:
    """The newest ``root/<name>/<version>/`` holding a manifest (what ``load_models`` serves unpinned), or None."""
    versions = [p.parent for p in (root / name).glob("*/manifest.json")]
    return max(versions, key=lambda p: version_key(p.name)) if versions else None


@dataclass(frozen=True)
class Refusal:
    """A model version under the models directory that is not served, and why."""

    name: str
    version: str
    path: str
    reason: str


@dataclass
class LoadReport:
    """What ``load_models`` served, what it refused, and the pins it could not honour."""

    models: dict[str, LoadedModel] = field(default_factory=dict)
    refused: list[Refusal] = field(default_factory=list)
    failed_pins: dict[str, str] = field(default_factory=dict)  # name → why the pinned version is not served

    def newer_refused(self) -> list[Refusal]:
        """Refused versions newer than the version of their name that is served (or of a name not served)."""
        served = {m.manifest.name: m.manifest.version for m in self.models.values()}
        return [r for r in self.refused if r.name not in served or version_key(r.version) > version_key(served[r.name])]


def load_models(root: Path, threads: int, pins: dict[str, str] | None = None) -> dict[str, LoadedModel]:
    """Newest valid version of every model below ``root`` (or the version ``pins`` names), keyed by task (pose
    models, imu_pose, imu_pose_velocity and flex_pose, by name)."""
    return load_model_report(root, threads, pins).models


def load_model_report(root: Path, threads: int, pins: dict[str, str] | None = None) -> LoadReport:
    """``load_models`` with the refusals: every ``<name>/<version>/`` folder holding a model file or a manifest is
    tried; one that cannot be served (no manifest, unreadable, sha256 or shapes differ) is logged as an error and
    listed, never silently passed over."""
    report = LoadReport()
    pins = pins or {}
    folders = sorted({p.parent for pattern in ("*/*/manifest.json", "*/*/model.onnx") for p in root.glob(pattern)})
    for folder in folders:
        name, version = folder.parent.name, folder.name
        if name in pins and pins[name] != version:
            continue
        try:
            if not (folder / "manifest.json").is_file():
                raise ModelMismatch(f"no manifest.json beside {folder / 'model.onnx'}")
            model = load_model(folder, threads)
        except Exception as exc:  # any broken model is refused, listed and logged; the others are still served
            log.error("refusing model %s: %s", folder, exc)
            report.refused.append(Refusal(name, version, str(folder), str(exc)))
            if name in pins:
                report.failed_pins[name] = f"pinned {name} {version} refused: {exc}"
            continue
        # pose models are several per task (placements, offline and streaming, sensor kinds): keyed by name
        task = model.manifest.name if model.manifest.task in POSE_TASKS else model.manifest.task
        models = report.models
        if task not in models or version_key(model.manifest.version) > version_key(models[task].manifest.version):
            models[task] = model
        log.info("loaded %s %s (%s)", model.manifest.name, model.manifest.version, task)
    for name, version in pins.items():
        if not (root / name / version).is_dir():
            report.failed_pins[name] = f"pinned {name} {version} is not under {root}"
            log.error("pinned model %s %s is not under %s", name, version, root)
    for refusal in report.newer_refused():
        log.error(
            "serving an older %s than the newest on disk: %s %s was refused (%s)",
            refusal.name,
            refusal.name,
            refusal.version,
            refusal.reason,
        )
    return report


def load_registry_models(
    tracking_uri: str | None, model_uris: list[str], cache_dir: Path, threads: int, report: LoadReport | None = None
) -> dict[str, LoadedModel]:
    """Models named by MLflow registry URIs, keyed by task; each failure is logged, skipped and added to
    ``report``'s refusals (the local model of its task, if any, is then served: /ready says so)."""
    from service.inference.mlflow_registry import fetch_registry_model

    models: dict[str, LoadedModel] = {}
    for uri in model_uris:
        try:
            if not tracking_uri:
                raise ValueError("set WEARMOCAP_MLFLOW_TRACKING_URI to the tracking server that holds the registry")
            model_dir = fetch_registry_model(tracking_uri, uri, cache_dir)
            model = load_model(model_dir, threads)
        except Exception as exc:  # a registry problem must not stop the service from serving the others
            log.error("refusing registry model %s: %s", uri, exc)
            if report is not None:
                report.refused.append(Refusal(uri, "registry", uri, str(exc)))
            continue
        model.source = f"{uri} (version {model_dir.name}) at {tracking_uri}"
        models[model.manifest.name if model.manifest.task in POSE_TASKS else model.manifest.task] = model
        log.info("loaded %s from the registry (%s)", model.manifest.name, model.source)
    return models
