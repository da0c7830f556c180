"""ONNX export with a dynamic batch dimension, a golden input/output pair and a parity check."""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np
import onnxruntime as ort
import torch
from torch import nn

from training.i2s.models import AlignmentNet, AssignmentEnsemble, AssignmentExport, AssignmentNet

log = logging.getLogger(__name__)

OPSET = 17
PARITY_ATOL = 1e-4
OUTPUT_NAMES = {"assignment": "probabilities", "alignment": "q_segment_imu"}


def export_module(model: nn.Module) -> nn.Module:
    """The exported graph of a trained net: softmax added for assignment; the alignment net already ends in
    unit quaternions (stereographic → quaternion, and the canonical frame if it has one)."""
    if isinstance(model, AssignmentNet | AssignmentEnsemble):
        return AssignmentExport(model).eval()
    if isinstance(model, AlignmentNet):
        return model.eval()
    raise TypeError(f"expected AssignmentNet, AssignmentEnsemble or AlignmentNet, got {type(model).__name__}")


def export_onnx(model: nn.Module, task: str, path: Path) -> Path:
    """Export with the TorchScript exporter, which emits native ONNX GRU/LSTM ops (fast in onnxruntime)."""
    wrapped = export_module(model)
    example = torch.zeros(1, 128, 6)  # batch 1: the RNN exporter warns about other sizes
    path.parent.mkdir(parents=True, exist_ok=True)
    out = OUTPUT_NAMES[task]
    torch.onnx.export(
        wrapped,
        (example,),
        str(path),
        input_names=["imu"],
        output_names=[out],
        dynamic_axes={"imu": {0: "batch"}, out: {0: "batch"}},
        opset_version=OPSET,
        dynamo=False,
    )
    return path


def golden_pair(model: nn.Module, imu: np.ndarray) -> dict[str, np.ndarray]:
    """Torch reference output on a fixed input: what the parity test compares onnxruntime against."""
    with torch.no_grad():
        ref = export_module(model)(torch.from_numpy(imu)).numpy()
    return {"imu": imu.astype(np.float32), "expected": ref.astype(np.float32)}


def onnx_parity(onnx_path: Path, golden: dict[str, np.ndarray]) -> float:
    """Max |onnxruntime − torch| on the golden input."""
    session = ort.InferenceSession(str(onnx_path), providers=["CPUExecutionProvider"])
    got = session.run(None, {"imu": golden["imu"]})[0]
    return float(np.max(np.abs(got - golden["expected"])))
