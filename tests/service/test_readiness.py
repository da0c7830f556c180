"""/ready tells the truth about model files: a refused newer version, a pin that cannot be served, strict mode."""

from __future__ import annotations

import logging
import shutil
from pathlib import Path

import pytest
from fastapi.testclient import TestClient

from service.app import create_app
from service.core.manifest import read_manifest, write_manifest
from service.settings import Settings


def _newer(root: Path, name: str, version: str = "0.0.2") -> Path:
    target = root / name / version
    shutil.copytree(root / name / "0.0.1", target)
    manifest = read_manifest(target / "manifest.json")
    manifest.version = version
    write_manifest(manifest, target / "manifest.json")
    return target


def _truncate(folder: Path) -> None:
    onnx = folder / "model.onnx"
    onnx.write_bytes(onnx.read_bytes()[:100])


def _change_sha(folder: Path) -> None:
    manifest = read_manifest(folder / "manifest.json")
    manifest.sha256 = "0" * 64
    write_manifest(manifest, folder / "manifest.json")


def _drop_manifest(folder: Path) -> None:
    (folder / "manifest.json").unlink()


@pytest.mark.parametrize(
    ("breaks", "reason"),
    [(_truncate, "sha256"), (_change_sha, "manifest says 000"), (_drop_manifest, "no manifest.json")],
)
def test_a_refused_newest_version_makes_ready_say_degraded(tiny_models: Path, caplog, breaks, reason) -> None:
    broken = _newer(tiny_models, "i2s_assignment")
    breaks(broken)
    caplog.set_level(logging.ERROR)
    with TestClient(create_app(Settings(models_dir=tiny_models))) as c:
        r = c.get("/ready")
        assert r.status_code == 200
        body = r.json()
        assert body["status"] == "degraded" and body["ready"] is True
        assert body["models"]["i2s_assignment"] == "0.0.1"  # what is actually served
        [refused] = body["refused"]
        assert refused["name"] == "i2s_assignment" and refused["version"] == "0.0.2"
        assert refused["path"].endswith("i2s_assignment/0.0.2") and reason in refused["reason"]
    assert any("refusing model" in rec.message and rec.levelno == logging.ERROR for rec in caplog.records)
    assert any("serving an older i2s_assignment" in rec.message for rec in caplog.records)


def test_ready_is_ok_when_every_file_is_served(tiny_models: Path) -> None:
    _newer(tiny_models, "i2s_assignment")
    with TestClient(create_app(Settings(models_dir=tiny_models))) as c:
        body = c.get("/ready").json()
        assert body == {
            "ready": True,
            "status": "ok",
            "models": {"i2s_alignment": "0.0.1", "i2s_assignment": "0.0.2"},
            "refused": [],
            "failed_pins": {},
        }


def test_a_pinned_version_that_cannot_load_is_never_replaced(tiny_models: Path) -> None:
    _truncate(_newer(tiny_models, "i2s_alignment"))
    settings = Settings(models_dir=tiny_models, model_versions="i2s_alignment=0.0.2")
    with TestClient(create_app(settings)) as c:
        r = c.get("/ready")
        assert r.status_code == 503
        assert r.json()["status"] == "unavailable"
        assert "pinned i2s_alignment 0.0.2 refused" in r.json()["failed_pins"]["i2s_alignment"]
        assert "i2s_alignment" not in c.get("/v1/models").json()  # not silently 0.0.1
    missing = Settings(models_dir=tiny_models, model_versions="i2s_assignment=9.9.9")
    with TestClient(create_app(missing)) as c:
        assert c.get("/ready").status_code == 503
        assert "is not under" in c.get("/ready").json()["failed_pins"]["i2s_assignment"]


def test_strict_models_refuses_to_start_with_a_refused_file(tiny_models: Path) -> None:
    _change_sha(_newer(tiny_models, "i2s_assignment"))
    with pytest.raises(RuntimeError, match="STRICT_MODELS.*i2s_assignment/0.0.2"):
        with TestClient(create_app(Settings(models_dir=tiny_models, strict_models=True))):
            pass
