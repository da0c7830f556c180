"""Int8 variants of a shipped model for faster CPU serving (onnxruntime quantisation).

Measured on the 2-core CI machine (``python -m benchmarks.bench_ort_vs_torch`` compares them): dynamic
quantisation (``ConvInteger``) is *slower* than float32 here, while static QDQ quantisation of the three
convolutions, calibrated on simulated training windows, runs them on the int8 (VNNI) kernels. The recurrent
layers stay float32 for the GRU (onnxruntime has no int8 GRU); for the LSTM, dynamic int8 weights
(``DynamicQuantizeLSTM``) are added when ``rnn=True``.

The quantised file is shipped as its own version beside the float32 one, with its own golden output and
evaluations: accuracy is measured on the shipped int8 file by the same ``training.cli evaluate`` command.
"""

from __future__ import annotations

import datetime as dt
import logging
import shutil
import tempfile
from pathlib import Path

import numpy as np
import onnxruntime as ort
from mlflow.tracking import MlflowClient
from onnxruntime.quantization import CalibrationDataReader, QuantFormat, QuantType, quantize_dynamic, quantize_static
from onnxruntime.quantization.shape_inference import quant_pre_process

from service.core.manifest import read_manifest, sha256_file, write_manifest
from training.i2s.config import ExperimentConfig
from training.i2s.data.windows import WindowSampler
from training.run_labels import record_shipped

log = logging.getLogger(__name__)

CALIBRATION_SEED = 7
# Gates on the golden input against the float32 torch reference. Probabilities: max |diff|. Quaternions: the
# median rotation angle between int8 and float32 outputs over all segment hypotheses (a few hypotheses of the
# wrong segment sit near the stereographic singularity and move more; accuracy is judged by the evaluations).
MAX_PROBABILITY_DIFF = 0.01
MAX_MEDIAN_QUAT_ANGLE_DEG = 1.0


class _Windows(CalibrationDataReader):
    def __init__(self, imu: np.ndarray, batch: int = 64) -> None:
        self.batches = iter([{"imu": imu[i : i + batch]} for i in range(0, len(imu), batch)])

    def get_next(self) -> dict[str, np.ndarray] | None:
        return next(self.batches, None)


def calibration_windows(cfg: ExperimentConfig, data_dir: Path, cache_dir: Path, n: int) -> np.ndarray:
    """``n`` simulated windows of the *training* subjects, with the run's own augmentations."""
    from training.i2s.data.split import load_clips, split_clips

    train, _, _ = split_clips(
        load_clips(cfg, data_dir, cache_dir), cfg.data.test_subjects, cfg.data.val_fraction, cfg.seed
    )
    return WindowSampler(train, cfg.augmentation).sample(np.random.default_rng(CALIBRATION_SEED), n).imu


def quantize_onnx(src: Path, dst: Path, calibration: np.ndarray, rnn: bool) -> str:
    """Static int8 QDQ convolutions (per-channel weights), optionally dynamic int8 LSTM; returns a description."""
    with tempfile.TemporaryDirectory() as tmp:
        pre = Path(tmp) / "pre.onnx"
        quant_pre_process(str(src), str(pre))
        conv = Path(tmp) / "conv.onnx"
        quantize_static(
            str(pre),
            str(conv),
            _Windows(calibration),
            quant_format=QuantFormat.QDQ,
            op_types_to_quantize=["Conv"],
            per_channel=True,
            activation_type=QuantType.QUInt8,
            weight_type=QuantType.QInt8,
        )
        text = f"int8 static QDQ Conv (per-channel weights, uint8 activations, {len(calibration)} calibration windows)"
        if rnn:
            quantize_dynamic(str(conv), str(dst), op_types_to_quantize=["LSTM"], weight_type=QuantType.QInt8)
            text += " + dynamic int8 LSTM weights"
        else:
            shutil.copy(conv, dst)
    return text


def ship_int8(src_dir: Path, version: str, data_dir: Path, cache_dir: Path, n_calibration: int, rnn: bool) -> Path:
    """``onnx_models/<name>/<src version>`` → ``onnx_models/<name>/<version>`` with an int8 model, its manifest
    (new sha256, the quantisation recorded, evaluations cleared until ``training.cli evaluate`` runs) and golden."""
    from training.i2s.ship import load_run_config

    manifest = read_manifest(src_dir / "manifest.json")
    cfg = ExperimentConfig.model_validate(load_run_config(manifest.mlflow["run_id"]))
    target = src_dir.parent / version
    if target.exists():
        raise FileExistsError(f"{target} exists; choose another version")
    target.mkdir(parents=True)
    try:
        calibration = calibration_windows(cfg, data_dir, cache_dir, n_calibration)
        described = quantize_onnx(src_dir / "model.onnx", target / "model.onnx", calibration, rnn)
        shutil.copy(src_dir / "golden.npz", target / "golden.npz")
        with np.load(target / "golden.npz") as z:
            golden = dict(z)
        parity = _gate(target / "model.onnx", golden, manifest.output_kind)
    except BaseException:
        shutil.rmtree(target)  # a refused file leaves no half-made version for the service to trip over
        raise
    manifest.version = version
    manifest.created_utc = dt.datetime.now(dt.UTC).isoformat(timespec="seconds")
    manifest.sha256 = sha256_file(target / "model.onnx")
    manifest.exporter = {**manifest.exporter, "quantization": described, "quantized_from": src_dir.name}
    manifest.parity_atol = float(np.ceil(parity * 1000) / 1000)  # measured, so the golden check stays true
    manifest.evaluations = []
    write_manifest(manifest, target / "manifest.json")
    record_shipped(MlflowClient(), manifest.mlflow["run_id"], manifest.name, version)
    log.info("int8 %s %s: golden max |diff| vs torch float32 %.3g", manifest.name, version, parity)
    return target


def _gate(onnx_path: Path, golden: dict[str, np.ndarray], output_kind: str) -> float:
    """Refuse an int8 file that moves the golden output too far; returns its max |diff| (the parity)."""
    got = ort.InferenceSession(str(onnx_path), providers=["CPUExecutionProvider"]).run(None, {"imu": golden["imu"]})[0]
    want = golden["expected"]
    parity = float(np.abs(got - want).max())
    if output_kind == "quaternion_per_segment":
        angle = np.degrees(2 * np.arccos(np.clip(np.abs((got * want).sum(-1)), 0.0, 1.0)))
        if np.median(angle) > MAX_MEDIAN_QUAT_ANGLE_DEG:
            raise ValueError(
                f"int8 quaternions differ by a median {np.median(angle):.2f} deg > "
                f"{MAX_MEDIAN_QUAT_ANGLE_DEG}; not shipped"
            )
    elif parity > MAX_PROBABILITY_DIFF:
        raise ValueError(f"int8 probabilities differ by {parity:.3g} > {MAX_PROBABILITY_DIFF}; not shipped")
    return parity
