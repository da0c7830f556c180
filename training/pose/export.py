"""ONNX export of a pose network, its golden pair, parity check and manifest (DESIGN.md §1)."""

from __future__ import annotations

import datetime as dt
from pathlib import Path

import numpy as np
import onnx
import onnxruntime as ort
import torch

from service.core.body import Body
from service.core.calibration import ACC_SCALE_MPS2, FEATURE_VERSION, features_per_frame
from service.core.manifest import Evaluation, Manifest, PoseSpec, TensorSpec
from training.pose.config import PoseConfig
from training.pose.data import BANDAI_LICENCE, MODEL_RATE_HZ
from training.pose.models import PoseNet, StreamingExport

OPSET = 17
PARITY_ATOL = 1e-4
TASK = "imu_pose"


def is_streaming(cfg: PoseConfig) -> bool:
    return cfg.model.kind == "lstm"


def export_pose_onnx(net: PoseNet, cfg: PoseConfig, path: Path) -> Path:
    """TorchScript exporter (native ONNX LSTM ops). Offline: features → rotations over any number of frames.
    Streaming: (features, h0, c0) → (rotations, h, c)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    F = features_per_frame(len(cfg.sensors))
    net = net.eval()
    x = torch.zeros(1, 16, F)
    if is_streaming(cfg):
        h = torch.zeros(net.layers, 1, net.hidden)
        torch.onnx.export(
            StreamingExport(net),
            (x, h, h.clone()),
            str(path),
            input_names=["features", "h0", "c0"],
            output_names=["rotations", "h", "c"],
            dynamic_axes={"features": {1: "frames"}, "rotations": {1: "frames"}},
            opset_version=OPSET,
            dynamo=False,
        )
    else:
        torch.onnx.export(
            net,
            (x,),
            str(path),
            input_names=["features"],
            output_names=["rotations"],
            dynamic_axes={"features": {0: "batch", 1: "frames"}, "rotations": {0: "batch", 1: "frames"}},
            opset_version=OPSET,
            dynamo=False,
        )
    return path


def golden_pair(net: PoseNet, features: np.ndarray, cfg: PoseConfig) -> dict[str, np.ndarray]:
    x = torch.from_numpy(features[None].astype(np.float32))
    with torch.no_grad():
        if is_streaming(cfg):
            h = torch.zeros(net.layers, 1, net.hidden)
            y, _, _ = net.step(x, h, h.clone())
        else:
            y = net(x)
    return {"features": x.numpy(), "expected": y.numpy().astype(np.float32)}


def onnx_parity(path: Path, golden: dict[str, np.ndarray], cfg: PoseConfig, net: PoseNet) -> float:
    session = ort.InferenceSession(str(path), providers=["CPUExecutionProvider"])
    feeds = {"features": golden["features"]}
    if is_streaming(cfg):
        z = np.zeros((net.layers, 1, net.hidden), np.float32)
        feeds |= {"h0": z, "c0": z}
    got = session.run(None, feeds)[0]
    return float(np.max(np.abs(got - golden["expected"])))


def build_pose_manifest(
    cfg: PoseConfig,
    net: PoseNet,
    version: str,
    sha256: str,
    body: Body,
    training_data: dict,
    evaluations: list[Evaluation],
    mlflow_info: dict[str, str],
) -> Manifest:
    F = features_per_frame(len(cfg.sensors))
    S = len(cfg.outputs)
    streaming = is_streaming(cfg)
    batch = 1 if streaming else "batch"
    inputs = [
        TensorSpec(
            name="features",
            shape=[batch, "frames", F],
            dtype="float32",
            description=f"service.core.calibration.pose_features ({FEATURE_VERSION}) of the sensors in pose.sensors "
            "order at 60 Hz: per non-root sensor R_root_segment (9, row-major) and its pelvis-relative free "
            f"acceleration / {ACC_SCALE_MPS2:g} m/s^2 in the pelvis frame (3); first the root's up vector and own "
            "free acceleration (6)",
        )
    ]
    outputs = [
        TensorSpec(
            name="rotations",
            shape=[batch, "frames", S, 3, 3],
            dtype="float32",
            description="R_root_segment of pose.output_segments (rotation matrices, pelvis frame)",
        )
    ]
    if streaming:
        state = [net.layers, 1, net.hidden]
        state_desc = f"LSTM state ({net.layers}, 1, {net.hidden}); zeros at the start of a stream"
        inputs += [TensorSpec(name=n, shape=state, dtype="float32", description=state_desc) for n in ("h0", "c0")]
        outputs += [TensorSpec(name=n, shape=state, dtype="float32", description=state_desc) for n in ("h", "c")]
    return Manifest(
        name=cfg.name,
        task=TASK,
        version=version,
        created_utc=dt.datetime.now(dt.UTC).isoformat(timespec="seconds"),
        inputs=inputs,
        outputs=outputs,
        output_kind="rotation_matrix_per_segment",
        sample_rate_hz=MODEL_RATE_HZ,
        window_samples=cfg.train.sequence_frames,
        hop_samples=1,
        channels=[f"{s}:{c}" for s in cfg.sensors for c in ("q_world_sensor", "acc")],
        units={"acc": "m/s^2", "q_world_sensor": "unit quaternion w, x, y, z (sensor's own world frame, z up)"},
        classes=list(cfg.outputs),
        quaternion_convention="Hamilton, scalar first (w, x, y, z), unit, w >= 0",
        pose=PoseSpec(
            sensors=list(cfg.sensors),
            output_segments=list(cfg.outputs),
            feature_version=FEATURE_VERSION,
            acc_scale_mps2=ACC_SCALE_MPS2,
            representation=cfg.model.representation,
            architecture=f"{cfg.model.kind} hidden {net.hidden} x {net.layers}",
            streaming=streaming,
            look_ahead_frames=cfg.model.look_ahead if streaming else cfg.train.context_frames,
            window_frames=1 if streaming else cfg.train.sequence_frames,
            context_frames=0 if streaming else cfg.train.context_frames,
            state_layers=net.layers if streaming else 0,
            state_hidden=net.hidden if streaming else 0,
            body=body.to_json(),
            body_height_m=round(body.height_m, 3),
        ),
        sha256=sha256,
        training_data=training_data | ({"licence": BANDAI_LICENCE} if training_data.get("bandai_namco") else {}),
        evaluations=evaluations,
        mlflow=mlflow_info,
        exporter={"torch": torch.__version__, "onnx": onnx.__version__, "opset": OPSET, "exporter": "torchscript"},
        parity_atol=PARITY_ATOL,
    )
