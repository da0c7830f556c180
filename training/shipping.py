"""What every task does to ship a model: its files under ``onnx_models/<name>/<version>/`` (docs/conventions.md) and the
registry entry recorded in its manifest."""

from __future__ import annotations

import shutil
from pathlib import Path

from mlflow.entities.model_registry import ModelVersion
from mlflow.models.model import ModelInfo
from mlflow.tracking import MlflowClient

from service.core.manifest import Manifest, write_manifest
from training.run_labels import record_shipped


def with_registry(manifest: Manifest, info: ModelInfo, registered: ModelVersion) -> Manifest:
    """The manifest naming the logged model and its registered version."""
    extra = {"model_uri": info.model_uri, "registered_version": str(registered.version)}
    return manifest.model_copy(update={"mlflow": manifest.mlflow | extra})


def ship_files(ship_to: Path, manifest: Manifest, onnx_path: Path, golden_path: Path) -> Path:
    """``model.onnx``, ``golden.npz`` and ``manifest.json`` under ``ship_to/<name>/<version>``; the folder."""
    shipped = ship_to / manifest.name / manifest.version
    shipped.mkdir(parents=True, exist_ok=True)
    shutil.copy(onnx_path, shipped / "model.onnx")
    shutil.copy(golden_path, shipped / "golden.npz")
    write_manifest(manifest, shipped / "manifest.json")
    if manifest.mlflow.get("run_id"):
        record_shipped(MlflowClient(), manifest.mlflow["run_id"], manifest.name, manifest.version)
    return shipped
