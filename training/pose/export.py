"""ONNX export of a pose network, its golden pair, parity check and manifest (docs/conventions.md)."""

from __future__ import annotations

import datetime as dt
import shutil
from pathlib import Path

import numpy as np
import onnx
import onnxruntime as ort
import torch

from service.core.body import Body
from service.core.calibration import ACC_SCALE_MPS2, FEATURE_VERSION, features_per_frame
from service.core.manifest import Evaluation, Manifest, PoseSpec, TensorSpec, read_manifest, sha256_file, write_manifest
from training.data.catalog import BANDAI_LICENCE
from training.pose.config import PoseConfig, is_streaming
from training.pose.data import MODEL_RATE_HZ
from training.pose.models import PoseEnsemble, PoseNet, StreamingExport

OPSET = 17
PARITY_ATOL = 1e-4
TASK = "imu_pose"


def export_pose_onnx(net: PoseNet, cfg: PoseConfig, path: Path) -> Path:
    """TorchScript exporter (native ONNX LSTM ops). Offline: features → rotations over any number of frames.
    Streaming: (features, h0, c0) → (rotations, h, c)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    F = features_per_frame(len(cfg.sensors))
    net = net.eval()
    x = torch.zeros(1, 16, F)
    if is_streaming(cfg):
        export_stateful(StreamingExport(net), x, torch.zeros(net.layers, 1, net.hidden), "rotations", path)
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


def export_stateful(module: torch.nn.Module, x: torch.Tensor, h: torch.Tensor, output: str, path: Path) -> Path:
    """A recurrent network's streaming graph: (features, h0, c0) → (``output``, h, c), the batch and frames
    symbolic: a batch of live sessions per call (service.inference.pose_batcher), each with its own state."""
    torch.onnx.export(
        module,
        (x, h, h.clone()),
        str(path),
        input_names=["features", "h0", "c0"],
        output_names=[output, "h", "c"],
        dynamic_axes={
            "features": {0: "batch", 1: "frames"},
            output: {0: "batch", 1: "frames"},
            **{name: {1: "batch"} for name in ("h0", "c0", "h", "c")},
        },
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


def state_specs(layers: int, hidden: int) -> tuple[list[TensorSpec], list[TensorSpec]]:
    """A streaming graph's LSTM state: its inputs ``h0``, ``c0`` and outputs ``h``, ``c``."""
    shape: list[int | str] = [layers, "batch", hidden]
    text = f"LSTM state ({layers}, batch, {hidden}); zeros at the start of a recording or stream"
    specs = [
        [TensorSpec(name=n, shape=shape, dtype="float32", description=text) for n in names]
        for names in (("h0", "c0"), ("h", "c"))
    ]
    return specs[0], specs[1]


def pose_feature_fields(
    sensors: list[str], training_data: dict, evaluations: list[Evaluation], mlflow_info: dict[str, str]
) -> dict:
    """What the manifest of every model that reads ``pose_features`` says alike (the pose and the pelvis velocity
    networks): its readings, rate and conventions, its data (with Bandai-Namco's licence where it trained on
    them), figures, run and exporter."""
    return {
        "created_utc": dt.datetime.now(dt.UTC).isoformat(timespec="seconds"),
        "sample_rate_hz": MODEL_RATE_HZ,
        "hop_samples": 1,
        "channels": [f"{s}:{c}" for s in sensors for c in ("q_world_sensor", "acc")],
        "units": {"acc": "m/s^2", "q_world_sensor": "unit quaternion w, x, y, z (sensor's own world frame, z up)"},
        "quaternion_convention": "Hamilton, scalar first (w, x, y, z), unit, w >= 0",
        "training_data": training_data | ({"licence": BANDAI_LICENCE} if training_data.get("bandai_namco") else {}),
        "evaluations": evaluations,
        "mlflow": mlflow_info,
        "exporter": {"torch": torch.__version__, "onnx": onnx.__version__, "opset": OPSET, "exporter": "torchscript"},
        "parity_atol": PARITY_ATOL,
    }


def build_pose_manifest(
    cfg: PoseConfig,
    net: PoseNet | PoseEnsemble,
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
    batch = "batch"
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
        state_in, state_out = state_specs(net.layers, net.hidden)
        inputs += state_in
        outputs += state_out
    return Manifest(
        name=cfg.name,
        task=TASK,
        version=version,
        inputs=inputs,
        outputs=outputs,
        output_kind="rotation_matrix_per_segment",
        window_samples=cfg.train.sequence_frames,
        classes=list(cfg.outputs),
        pose=PoseSpec(
            sensors=list(cfg.sensors),
            output_segments=list(cfg.outputs),
            feature_version=FEATURE_VERSION,
            acc_scale_mps2=ACC_SCALE_MPS2,
            representation=cfg.model.representation,
            architecture=(f"mean of {len(cfg.train.ensemble_of)} × " if cfg.train.ensemble_of else "")
            + f"{cfg.model.kind} hidden {net.hidden} x {net.layers}"
            + (", each also on the mirror image" if cfg.train.ensemble_mirror else ""),
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
        **pose_feature_fields(cfg.sensors, training_data, evaluations, mlflow_info),
    )


def free_batch_dimension(model_dir: Path, version: str, models_dir: Path) -> Path:
    """Ship a streaming pose model exported with a batch of one (versions 1.0.0) as ``version`` whose batch
    dimension is symbolic, so that the service can run several live sessions in one call: the same weights and
    nodes, only the graph's declared input and output shapes change. Checked before anything is written: the golden
    pair still holds, and a batch of three sessions gives each session's answer and state exactly as three calls
    do. The manifest says what it was derived from; the folder written."""
    manifest = read_manifest(model_dir / "manifest.json")
    if manifest.pose is None or not manifest.pose.streaming:
        raise ValueError(f"{model_dir} is not a streaming pose model")
    model = onnx.load(str(model_dir / "model.onnx"))
    batch_axis = {"features": 0, "rotations": 0, "h0": 1, "c0": 1, "h": 1, "c": 1}
    for value in [*model.graph.input, *model.graph.output]:
        dim = value.type.tensor_type.shape.dim[batch_axis[value.name]]
        if dim.dim_param == "batch":
            raise ValueError(f"{model_dir}: its batch dimension is symbolic already")
        dim.Clear()
        dim.dim_param = "batch"
    del model.graph.value_info[:]  # inferred shapes of the batch of one; onnxruntime infers them again
    data = model.SerializeToString()
    session = ort.InferenceSession(data, providers=["CPUExecutionProvider"])
    with np.load(model_dir / "golden.npz") as z:
        golden = dict(z)
    L, H = manifest.pose.state_layers, manifest.pose.state_hidden
    zero = np.zeros((L, 1, H), np.float32)
    got = session.run(None, {"features": golden["features"], "h0": zero, "c0": zero})[0]
    if np.max(np.abs(got - golden["expected"])) > manifest.parity_atol:
        raise ValueError(f"{model_dir}: the graph with a symbolic batch no longer reproduces its golden pair")
    rng = np.random.default_rng(0)
    x = rng.normal(size=(3, 7, golden["features"].shape[-1])).astype(np.float32)
    h, c = (0.5 * rng.normal(size=(L, 3, H)).astype(np.float32) for _ in range(2))
    together = session.run(None, {"features": x, "h0": h, "c0": c})
    for b in range(3):
        alone = session.run(None, {"features": x[b : b + 1], "h0": h[:, b : b + 1], "c0": c[:, b : b + 1]})
        for name, one, many in zip(("rotations", "h", "c"), alone, together, strict=True):
            part = many[b : b + 1] if name == "rotations" else many[:, b : b + 1]
            if np.max(np.abs(one - part)) > 1e-5:
                raise ValueError(f"{model_dir}: session {b}'s {name} differs when run in a batch")
    target = models_dir / manifest.name / version
    if target.exists():
        raise FileExistsError(f"{target} exists")
    target.mkdir(parents=True)
    (target / "model.onnx").write_bytes(data)
    shutil.copy(model_dir / "golden.npz", target / "golden.npz")
    shapes = {}
    for spec in [*manifest.inputs, *manifest.outputs]:
        shape = list(spec.shape)
        shape[batch_axis[spec.name]] = "batch"
        shapes[spec.name] = shape
    derived = manifest.model_copy(
        update={
            "version": version,
            "created_utc": dt.datetime.now(dt.UTC).isoformat(timespec="seconds"),
            "sha256": sha256_file(target / "model.onnx"),
            "inputs": [s.model_copy(update={"shape": shapes[s.name]}) for s in manifest.inputs],
            "outputs": [s.model_copy(update={"shape": shapes[s.name]}) for s in manifest.outputs],
            "exporter": {
                **manifest.exporter,
                "derived_from": f"{manifest.name}/{manifest.version}",
                "derivation": "batch dimension made symbolic (training.pose.export.free_batch_dimension); same "
                "weights and nodes",
            },
        }
    )
    write_manifest(derived, target / "manifest.json")
    return target
