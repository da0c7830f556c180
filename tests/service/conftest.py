"""Tiny but real ONNX models (onnx.helper) with manifests, for API tests independent of training."""

from __future__ import annotations

import datetime as dt
from pathlib import Path

import numpy as np
import onnx
import pytest
from fastapi.testclient import TestClient
from onnx import TensorProto, helper, numpy_helper

from service.app import create_app
from service.core.manifest import FlexSpec, Manifest, TensorSpec, sha256_file, write_manifest
from service.core.segments import SEGMENTS
from service.settings import Settings


def _assignment_graph() -> onnx.ModelProto:
    """probabilities = softmax(mean_t(imu) @ W + b), W picks the class from the mean gyroscope x sign."""
    rng = np.random.default_rng(0)
    W = numpy_helper.from_array(rng.normal(size=(6, 7)).astype(np.float32), "W")
    b = numpy_helper.from_array(np.zeros(7, dtype=np.float32), "b")
    axes = numpy_helper.from_array(np.array([1], dtype=np.int64), "axes")
    nodes = [
        helper.make_node("ReduceMean", ["imu", "axes"], ["m"], keepdims=0),
        helper.make_node("MatMul", ["m", "W"], ["z0"]),
        helper.make_node("Add", ["z0", "b"], ["z"]),
        helper.make_node("Softmax", ["z"], ["probabilities"], axis=-1),
    ]
    graph = helper.make_graph(
        nodes,
        "tiny_assignment",
        [helper.make_tensor_value_info("imu", TensorProto.FLOAT, ["batch", 128, 6])],
        [helper.make_tensor_value_info("probabilities", TensorProto.FLOAT, ["batch", 7])],
        [W, b, axes],
    )
    return helper.make_model(graph, opset_imports=[helper.make_opsetid("", 18)], ir_version=9)


def _alignment_graph() -> onnx.ModelProto:
    """q_segment_imu = normalise(reshape(mean_t(imu) @ W + b)), b a unit quaternion per segment."""
    W = numpy_helper.from_array(np.full((6, 28), 0.01, dtype=np.float32), "W")
    b = numpy_helper.from_array(np.tile([1.0, 0.2, 0.0, 0.0], 7).astype(np.float32), "b")
    axes = numpy_helper.from_array(np.array([1], dtype=np.int64), "axes")
    last = numpy_helper.from_array(np.array([-1], dtype=np.int64), "last")
    shape = numpy_helper.from_array(np.array([-1, 7, 4], dtype=np.int64), "shape")
    nodes = [
        helper.make_node("ReduceMean", ["imu", "axes"], ["m"], keepdims=0),
        helper.make_node("MatMul", ["m", "W"], ["z0"]),
        helper.make_node("Add", ["z0", "b"], ["z"]),
        helper.make_node("Reshape", ["z", "shape"], ["q0"]),
        helper.make_node("ReduceL2", ["q0", "last"], ["n"], keepdims=1),
        helper.make_node("Div", ["q0", "n"], ["q_segment_imu"]),
    ]
    graph = helper.make_graph(
        nodes,
        "tiny_alignment",
        [helper.make_tensor_value_info("imu", TensorProto.FLOAT, ["batch", 128, 6])],
        [helper.make_tensor_value_info("q_segment_imu", TensorProto.FLOAT, ["batch", 7, 4])],
        [W, b, axes, last, shape],
    )
    return helper.make_model(graph, opset_imports=[helper.make_opsetid("", 18)], ir_version=9)


def write_tiny_model(root: Path, task: str) -> Path:
    name = task
    target = root / name / "0.0.1"
    target.mkdir(parents=True)
    graph = _assignment_graph() if task == "i2s_assignment" else _alignment_graph()
    onnx.save(graph, target / "model.onnx")
    out = (
        TensorSpec(name="probabilities", shape=["batch", 7], dtype="float32")
        if task == "i2s_assignment"
        else TensorSpec(name="q_segment_imu", shape=["batch", 7, 4], dtype="float32")
    )
    manifest = Manifest(
        name=name,
        task=task,
        version="0.0.1",
        created_utc=dt.datetime.now(dt.UTC).isoformat(),
        inputs=[TensorSpec(name="imu", shape=["batch", 128, 6], dtype="float32")],
        outputs=[out],
        output_kind="probabilities" if task == "i2s_assignment" else "quaternion_per_segment",
        sample_rate_hz=60.0,
        window_samples=128,
        hop_samples=16,
        channels=["acc_x", "acc_y", "acc_z", "gyr_x", "gyr_y", "gyr_z"],
        units={"acc": "m/s^2", "gyr": "rad/s"},
        classes=list(SEGMENTS),
        sha256=sha256_file(target / "model.onnx"),
    )
    write_manifest(manifest, target / "manifest.json")
    return target


# A tiny flex model: (channels, rate Hz, window, value range, joints, components) per task.
TINY_POSE = {
    "flex_pose": (
        ["left_elbow", "right_elbow", "left_knee", "right_knee"],
        20.0,
        100,
        [0.0, 4095.0],
        ["LeftElbow", "RightElbow", "LeftKnee", "RightKnee"],
        ["flexion"],
    ),
}


def tiny_pose_weights(task: str) -> np.ndarray:
    channels, _, _, _, joints, components = TINY_POSE[task]
    rng = np.random.default_rng(1)
    return (rng.normal(size=(len(channels), len(joints) * len(components))) * 0.01).astype(np.float32)


def write_tiny_pose_model(root: Path, task: str) -> Path:
    """pose = reshape(mean_t(x) @ W): a (batch, joints, components) output whose values a test can recompute."""
    channels, rate, window, value_range, joints, components = TINY_POSE[task]
    W = numpy_helper.from_array(tiny_pose_weights(task), "W")
    axes = numpy_helper.from_array(np.array([1], dtype=np.int64), "axes")
    shape = numpy_helper.from_array(np.array([-1, len(joints), len(components)], dtype=np.int64), "shape")
    nodes = [
        helper.make_node("ReduceMean", ["x", "axes"], ["m"], keepdims=0),
        helper.make_node("MatMul", ["m", "W"], ["z"]),
        helper.make_node("Reshape", ["z", "shape"], ["pose"]),
    ]
    graph = helper.make_graph(
        nodes,
        f"tiny_{task}",
        [helper.make_tensor_value_info("x", TensorProto.FLOAT, ["batch", window, len(channels)])],
        [helper.make_tensor_value_info("pose", TensorProto.FLOAT, ["batch", len(joints), len(components)])],
        [W, axes, shape],
    )
    target = root / task / "0.0.1"
    target.mkdir(parents=True)
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 18)], ir_version=9)
    onnx.save(model, target / "model.onnx")
    manifest = Manifest(
        name=task,
        task=task,
        version="0.0.1",
        created_utc=dt.datetime.now(dt.UTC).isoformat(),
        inputs=[TensorSpec(name="x", shape=["batch", window, len(channels)], dtype="float32")],
        outputs=[TensorSpec(name="pose", shape=["batch", len(joints), len(components)], dtype="float32")],
        output_kind="joint_angles_deg",
        sample_rate_hz=rate,
        window_samples=window,
        hop_samples=1,
        channels=channels,
        units={"flex": "counts_12bit"},
        classes=[],
        joints=joints,
        joint_components=components,
        value_range=value_range,
        flex=FlexSpec(
            architecture="window mean times a matrix (a test model)",
            calibration=False,
            median=False,
            steps=window,
            latency_samples=0,
            angle_convention="test",
        ),
        sha256=sha256_file(target / "model.onnx"),
    )
    write_manifest(manifest, target / "manifest.json")
    return target


@pytest.fixture
def tiny_models(tmp_path: Path) -> Path:
    root = tmp_path / "onnx_models"
    write_tiny_model(root, "i2s_assignment")
    write_tiny_model(root, "i2s_alignment")
    return root


@pytest.fixture
def client(tiny_models: Path):
    settings = Settings(models_dir=tiny_models, max_body_bytes=2_000_000, stream_queue_limit=64)
    with TestClient(create_app(settings)) as c:
        yield c
