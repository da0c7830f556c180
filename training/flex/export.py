"""ONNX export of a flex network, its parity check and manifest (docs/conventions.md)."""

from __future__ import annotations

import datetime as dt
from pathlib import Path

import numpy as np
import onnx
import onnxruntime as ort
import torch

from service.core.joint_angles import ANGLE_CONVENTION, JOINT_COMPONENTS
from service.core.manifest import Evaluation, FlexSpec, Manifest, ReadoutCheckSpec, TensorSpec
from training.flex.config import FlexConfig
from training.flex.models import FlexEnsemble, FlexNet
from training.flex.simulate import ADC_MAX, AMP_GAIN, DIVIDER_OHM, FLEX_RATE_HZ, VCC

OPSET = 17
TASK = "flex_pose"


def export_flex_onnx(net: FlexNet | FlexEnsemble, path: Path) -> Path:
    """TorchScript exporter: ``counts`` (batch, window, channels) → ``angles`` (batch, joints, 3)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    x = torch.zeros(2, net.cfg.window, net.input_min.shape[-1])
    torch.onnx.export(
        net.eval(),
        (x,),
        str(path),
        input_names=["counts"],
        output_names=["angles"],
        dynamic_axes={"counts": {0: "batch"}, "angles": {0: "batch"}},
        opset_version=OPSET,
        dynamo=False,
    )
    return path


def onnx_parity(path: Path, golden: dict[str, np.ndarray]) -> float:
    session = ort.InferenceSession(str(path), providers=["CPUExecutionProvider"])
    got = session.run(None, {"counts": golden["counts"]})[0]
    return float(np.max(np.abs(got - golden["expected"])))


# the simulated suit's channels; a model that reads resistance back depends on the read-out's parts
_SUIT_UNITS = {
    False: "12-bit ADC counts (0-4095), Chen et al. 2024 eq. 1",
    True: f"12-bit ADC counts (0-4095) over {VCC:g} V, Chen et al. 2024 eq. 1 with R_i {DIVIDER_OHM / 1000:g} kΩ "
    f"and G {AMP_GAIN:g} (read back to resistance by the model)",
}


def build_flex_manifest(
    cfg: FlexConfig,
    net: FlexNet | FlexEnsemble,
    version: str,
    sha256: str,
    training_data: dict,
    evaluations: list[Evaluation],
    mlflow_info: dict[str, str],
    channels: list[str] | None = None,
    units: dict[str, str] | None = None,
    value_range: list[float] | None = None,
    sample_rate_hz: float = FLEX_RATE_HZ,
    joints: list[str] | None = None,
    components: list[str] | None = None,
    simulated_sensor: str = "training.flex.simulate (resistive strips, Chen et al. 2024 eq. 1, 12-bit)",
    angle_convention: str = ANGLE_CONVENTION,
    readout_check: ReadoutCheckSpec | None = None,
) -> Manifest:
    channels = channels or [f"{j}_flex" for j in cfg.sensors]
    joints = joints or list(cfg.joints)
    components = components or list(JOINT_COMPONENTS)
    W = cfg.model.window
    return Manifest(
        name=cfg.name,
        task=TASK,
        version=version,
        created_utc=dt.datetime.now(dt.UTC).isoformat(timespec="seconds"),
        inputs=[
            TensorSpec(
                name="counts",
                shape=["batch", W, len(channels)],
                dtype="float32",
                description=f"the last {W} readings of the channels in 'channels' order, oldest first, raw",
            )
        ],
        outputs=[
            TensorSpec(
                name="angles",
                shape=["batch", len(joints), len(components)],
                dtype="float32",
                description=f"joint angles in degrees of 'joints' x 'joint_components', at the sample "
                f"{net.latency_samples} before the window's last",
            )
        ],
        output_kind="joint_angles_deg",
        sample_rate_hz=sample_rate_hz,
        window_samples=W,
        hop_samples=1,
        channels=channels,
        units=units or {c: _SUIT_UNITS[cfg.model.input_norm == "log_resistance"] for c in channels},
        classes=[],
        joints=joints,
        joint_components=components,
        value_range=value_range if value_range is not None else ([0.0, float(ADC_MAX)] if units is None else None),
        flex=FlexSpec(
            architecture=f"{cfg.variant} (Chen et al. 2024 §3.4, appendix B)"
            + (f", the mean of {cfg.train.members} networks of consecutive seeds" if cfg.train.members > 1 else ""),
            calibration=cfg.model.calibration,
            median=cfg.model.median,
            steps=cfg.model.steps,
            latency_samples=net.latency_samples,
            angle_convention=angle_convention,
            simulated_sensor=simulated_sensor,
            readout_check=readout_check,
            input_norm=cfg.model.input_norm,
        ),
        sha256=sha256,
        training_data=training_data,
        evaluations=evaluations,
        mlflow=mlflow_info,
        exporter={"torch": torch.__version__, "onnx": onnx.__version__, "opset": OPSET, "exporter": "torchscript"},
        parity_atol=1e-3,
    )
