"""The generic flex pose route: 503 until a flex model is loaded, then whatever its manifest declares."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from fastapi.testclient import TestClient

from service.app import create_app
from service.settings import Settings
from tests.service.conftest import TINY_POSE, tiny_pose_weights, write_tiny_model, write_tiny_pose_model


@pytest.fixture
def pose_client(tmp_path: Path):
    root = tmp_path / "onnx_models"
    write_tiny_model(root, "i2s_assignment")
    for task in TINY_POSE:
        write_tiny_pose_model(root, task)
    with TestClient(create_app(Settings(models_dir=root))) as c:
        yield c


def _block(task: str, n: int | None = None, seed: int = 0) -> np.ndarray:
    channels, _, window, value_range, _, _ = TINY_POSE[task]
    rng = np.random.default_rng(seed)
    x = rng.uniform(1000, 3000, size=(n or window, len(channels)))
    return x if value_range else x / 1000.0


def test_pose_routes_answer_503_while_no_pose_model_is_loaded(client: TestClient) -> None:
    from service.api.schemas import EXAMPLE_POSE_IMU

    r = client.post("/v1/pose/flex", json={"blocks": [{"samples": _block("flex_pose").tolist()}]})
    assert r.status_code == 503
    assert "no flex_pose model is loaded" in r.json()["detail"] and "i2s_assignment" in r.json()["detail"]
    r = client.post("/v1/pose/imu", json=EXAMPLE_POSE_IMU)
    assert r.status_code == 503 and r.json()["detail"] == "no imu_pose model is loaded"


def test_flex_pose_returns_the_declared_joints_and_angles(pose_client: TestClient) -> None:
    blocks = [_block("flex_pose", seed=k) for k in range(3)]
    r = pose_client.post("/v1/pose/flex", json={"blocks": [{"samples": b.tolist()} for b in blocks]})
    assert r.status_code == 200, r.text
    body = r.json()
    assert body["output_kind"] == "joint_angles_deg" and body["model_versions"] == {"flex_pose": "0.0.1"}
    joints = TINY_POSE["flex_pose"][4]
    for block, result in zip(blocks, body["results"], strict=True):
        expected = block.mean(axis=0) @ tiny_pose_weights("flex_pose")
        got = [result["joint_angles_deg"][j]["flexion"] for j in joints]
        np.testing.assert_allclose(got, expected, rtol=1e-4)
        assert result["joint_rotations"] is None


def test_flex_blocks_at_another_rate_are_resampled(pose_client: TestClient) -> None:
    block = _block("flex_pose", n=210)  # 210 readings at 40 Hz: 105 at 20 Hz, the last 100 are used
    r = pose_client.post("/v1/pose/flex", json={"blocks": [{"samples": block.tolist(), "sample_rate_hz": 40.0}]})
    assert r.status_code == 200, r.text


@pytest.mark.parametrize(
    "samples, rate, fragment",
    [
        (_block("flex_pose")[:, :3], None, "every sample needs 4 values (left_elbow, right_elbow, left_knee"),
        (_block("flex_pose", n=99), None, "at 20 Hz a window has 100 samples, got 99"),
        (_block("flex_pose", n=150), 40.0, "at 40 Hz a window needs at least 200 samples"),
        (np.full((100, 4), 5000.0), None, "values must lie in [0, 4095], got [5000, 5000]"),
        (np.full((100, 4), -1.0), None, "values must lie in [0, 4095]"),
        (np.full((100, 4), np.nan), None, "finite"),
        (_block("flex_pose"), 0.5, "sample_rate_hz must be in [1, 2000]"),
    ],
)
def test_bad_pose_blocks_get_a_422_that_says_why(pose_client: TestClient, samples, rate, fragment: str) -> None:
    block = {"samples": samples.tolist()} | ({"sample_rate_hz": rate} if rate else {})
    if np.isnan(samples).any():
        text = json.dumps({"blocks": [block]})  # NaN literals: valid for Python's json, not for the standard
        r = pose_client.post("/v1/pose/flex", content=text, headers={"content-type": "application/json"})
    else:
        r = pose_client.post("/v1/pose/flex", json={"blocks": [block]})
    assert r.status_code == 422
    assert fragment in r.json()["detail"], r.json()["detail"]


def test_models_endpoint_lists_the_pose_contract(pose_client: TestClient) -> None:
    flex = pose_client.get("/v1/models").json()["flex_pose"]
    manifest = flex["manifest"] if "manifest" in flex else flex
    assert manifest["channels"][0] == "left_elbow" and manifest["joints"][0] == "LeftElbow"
    assert manifest["value_range"] == [0.0, 4095.0]


def test_a_pose_manifest_that_does_not_describe_its_tensors_is_refused(tmp_path: Path) -> None:
    from service.core.manifest import read_manifest
    from service.inference.registry import load_models

    root = tmp_path / "onnx_models"
    target = write_tiny_pose_model(root, "flex_pose")
    manifest = read_manifest(target / "manifest.json").model_dump()
    manifest["joints"] = manifest["joints"][:3]  # the output has 4 joints
    (target / "manifest.json").write_text(json.dumps(manifest))
    with pytest.raises(ValueError, match=r"output of shape \['batch', 3, 1\]"):
        read_manifest(target / "manifest.json")
    assert load_models(root, 1) == {}  # refused with a log line, nothing served
