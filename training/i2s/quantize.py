"""Int8 variants of a shipped model for faster CPU serving (onnxruntime quantisation).

Measured on the 2-core CI machine (``python -m benchmarks.bench_ort_vs_torch`` compares them): dynamic
quantisation (``ConvInteger``) is *slower* than float32 here, while static QDQ quantisation of the three
convolutions, calibrated on simulated training windows, runs them on the int8 (VNNI) kernels. The recurrent
layers stay float32 for the GRU (onnxruntime has no int8 GRU); for the LSTM, dynamic int8 weights
(``DynamicQuantizeLSTM``) are added when ``rnn=True``.

The calibration windows are simulated training windows of the run (the default) or, with ``calibrate_on="real"``,
windows of the run's real training recordings (what a model fine-tuned on real people sees when served). With
``float_first_conv`` the convolutions that read the six raw sensor channels stay float32: on the served assignment
they moved most of the answers that int8 changed (docs/models.md, "Served assignment 1.12.0").

The quantised file is shipped as its own version beside the float32 one, with its own golden output and
evaluations: accuracy is measured on the shipped int8 file by the same ``training.cli evaluate`` command, and a
model fine-tuned on real people is judged on people it has not seen by quantising its recipe's leave-one-person-out
folds the same way (``quantize_folds``), each calibrated on its own training people only.
"""

from __future__ import annotations

import datetime as dt
import logging
import shutil
import tempfile
from pathlib import Path

import mlflow
import numpy as np
import onnx
import onnxruntime as ort
from mlflow.tracking import MlflowClient
from onnxruntime.quantization import CalibrationDataReader, QuantFormat, QuantType, quantize_dynamic, quantize_static
from onnxruntime.quantization.shape_inference import quant_pre_process

from service.core.manifest import read_manifest, sha256_file, write_manifest
from service.core.recordings import RealRecording, read_all_real, read_recording
from service.core.windowing import sliding_windows
from training.i2s.config import ExperimentConfig
from training.i2s.data.windows import WindowSampler
from training.i2s.models import is_geometry_convolution
from training.run_labels import record_shipped
from training.snapshot import local_run_id

log = logging.getLogger(__name__)

CALIBRATION_SEED = 7
# Gates on the golden input against the float32 torch reference. Probabilities: max |diff|. Quaternions: the
# median rotation angle between int8 and float32 outputs over all segment hypotheses (a few hypotheses of the
# wrong segment sit near the stereographic singularity and move more; accuracy is judged by the evaluations).
MAX_PROBABILITY_DIFF = 0.01
MAX_MEDIAN_QUAT_ANGLE_DEG = 1.0
CALIBRATE_ON = ("simulated", "real")


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


def real_calibration_windows(names: list[str], data_dir: Path, n: int) -> np.ndarray:
    """``n`` windows drawn alike from every labelled sensor window of the real recordings ``names`` (a model's real
    training recordings: never a person it is scored on)."""
    if not names:
        raise ValueError("the model trained on no real recording: calibrate on simulated windows")
    windows = np.concatenate(
        [
            sliding_windows(s.imu.astype(np.float32))
            for r in (read_recording(data_dir, name) for name in names)
            for s in r.sensors
            if s.segment is not None
        ]
    )
    pick = np.random.default_rng(CALIBRATION_SEED).choice(len(windows), size=min(n, len(windows)), replace=False)
    return np.ascontiguousarray(windows[np.sort(pick)])


def model_calibration_windows(
    cfg: ExperimentConfig, calibrate_on: str, data_dir: Path, cache_dir: Path, n: int
) -> np.ndarray:
    if calibrate_on not in CALIBRATE_ON:
        raise ValueError(f"calibrate_on must be one of {CALIBRATE_ON}; got {calibrate_on!r}")
    if calibrate_on == "real":
        return real_calibration_windows(cfg.data.real_train_recordings, data_dir, n)
    return calibration_windows(cfg, data_dir, cache_dir, n)


def input_convolutions(onnx_path: Path) -> list[str]:
    """Names of the convolutions whose weights read six input channels: those applied to the raw sensor window."""
    model = onnx.load(str(onnx_path))
    shapes = {w.name: list(w.dims) for w in model.graph.initializer}
    return [
        n.name
        for n in model.graph.node
        if n.op_type == "Conv" and len(n.input) > 1 and shapes.get(n.input[1], [0, 0])[1] == 6
    ]


def geometry_convolutions(onnx_path: Path) -> list[str]:
    """Names of the convolutions of the functional axes (``is_geometry_convolution``): one-hot kernels that shift a
    signal by whole samples. They are arithmetic on the window, not learnt features, and stay float32."""
    graph = onnx.load(str(onnx_path)).graph
    return [n.name for n in graph.node if n.op_type == "Conv" and is_geometry_convolution(n.name)]


def quantize_onnx(
    src: Path, dst: Path, calibration: np.ndarray, rnn: bool, float_first_conv: bool = False, calibrated_on: str = ""
) -> str:
    """Static int8 QDQ convolutions (per-channel weights), optionally dynamic int8 LSTM and the input convolutions
    kept float32; returns a description."""
    with tempfile.TemporaryDirectory() as tmp:
        pre = Path(tmp) / "pre.onnx"
        quant_pre_process(str(src), str(pre))
        conv = Path(tmp) / "conv.onnx"
        excluded = (input_convolutions(pre) if float_first_conv else []) + geometry_convolutions(pre)
        quantize_static(
            str(pre),
            str(conv),
            _Windows(calibration),
            quant_format=QuantFormat.QDQ,
            op_types_to_quantize=["Conv"],
            per_channel=True,
            activation_type=QuantType.QUInt8,
            weight_type=QuantType.QInt8,
            nodes_to_exclude=excluded,
        )
        text = f"int8 static QDQ Conv (per-channel weights, uint8 activations, {len(calibration)} calibration windows"
        text += f", {calibrated_on})" if calibrated_on else ")"
        if float_first_conv:
            text += f"; float32 input convolutions {input_convolutions(pre)}"
        if geometry := geometry_convolutions(pre):
            text += f"; float32 geometry convolutions {geometry}"
        if rnn:
            quantize_dynamic(str(conv), str(dst), op_types_to_quantize=["LSTM"], weight_type=QuantType.QInt8)
            text += " + dynamic int8 LSTM weights"
        else:
            shutil.copy(conv, dst)
    return text


def ship_int8(
    src_dir: Path,
    version: str,
    data_dir: Path,
    cache_dir: Path,
    n_calibration: int,
    rnn: bool,
    calibrate_on: str = "simulated",
    float_first_conv: bool = False,
    max_probability_diff: float = MAX_PROBABILITY_DIFF,
) -> Path:
    """``onnx_models/<name>/<src version>`` → ``onnx_models/<name>/<version>`` with an int8 model, its manifest
    (new sha256, the quantisation recorded, evaluations cleared until ``training.cli evaluate`` runs) and golden."""
    from training.i2s.ship import load_run_config

    manifest = read_manifest(src_dir / "manifest.json")
    cfg = ExperimentConfig.model_validate(load_run_config(local_run_id(manifest.mlflow["run_id"])))
    target = src_dir.parent / version
    if target.exists():
        raise FileExistsError(f"{target} exists; choose another version")
    target.mkdir(parents=True)
    try:
        calibration = model_calibration_windows(cfg, calibrate_on, data_dir, cache_dir, n_calibration)
        described = quantize_onnx(
            src_dir / "model.onnx",
            target / "model.onnx",
            calibration,
            rnn,
            float_first_conv,
            f"{calibrate_on} training windows",
        )
        shutil.copy(src_dir / "golden.npz", target / "golden.npz")
        with np.load(target / "golden.npz") as z:
            golden = dict(z)
        parity = _gate(target / "model.onnx", golden, manifest.output_kind, max_probability_diff)
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


def _gate(
    onnx_path: Path, golden: dict[str, np.ndarray], output_kind: str, max_probability_diff: float = MAX_PROBABILITY_DIFF
) -> float:
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
    elif parity > max_probability_diff:
        raise ValueError(f"int8 probabilities differ by {parity:.3g} > {max_probability_diff}; not shipped")
    return parity


def quantize_folds(
    summary_run_id: str,
    data_dir: Path,
    cache_dir: Path,
    n_calibration: int,
    rnn: bool,
    calibrate_on: str,
    float_first_conv: bool,
) -> str:
    """Quantise every fold model of a ``real-loso`` summary run as ``ship_int8`` quantises a shipped file (each fold
    calibrated on its own training windows, so never on the person it is scored on), score each on its held-out
    person as the fold run did (one tracked run per fold, ``quantized_from`` the fold), and write their summary run as
    ``real-loso`` writes one: ``real-table``, ``swing-table`` and ``calibrate`` read it alike. Returns its run id."""
    from training.i2s.export import onnx_parity
    from training.i2s.pipeline import fold_figures, log_real_evaluation, log_real_loso_summary
    from training.i2s.ship import load_run_config
    from training.tracking import download_onnx, setup_tracking

    client = MlflowClient()
    summary = local_run_id(summary_run_id)
    tags = client.get_run(summary).data.tags
    folds = {k.removeprefix("fold_run."): v for k, v in tags.items() if k.startswith("fold_run.")}
    if not folds:
        raise ValueError(f"run {summary_run_id} is not a real-loso summary run (no fold_run.* tags)")
    persons: dict[str, list[RealRecording]] = {}
    for recording in read_all_real(data_dir):
        persons.setdefault(recording.subject, []).append(recording)
    runs = {person: client.get_run(local_run_id(fold_run)) for person, fold_run in sorted(folds.items())}
    for person, fold in runs.items():  # every fold checked before any is quantised
        if "model_uri" not in fold.data.tags:
            raise ValueError(
                f"fold run {fold.info.run_id} ({person}) has no model in this store (a snapshot keeps none): quantise "
                "its folds in the store that trained them, or run real-loso again"
            )
        scored = {k.removeprefix("n_windows.") for k in fold.data.metrics if k.startswith("n_windows.")}
        here = {r.name.replace("/", ".") for r in persons.get(person, [])}
        if scored != here:
            raise ValueError(
                f"fold {person} was scored on {sorted(scored)}, the data directory holds {sorted(here)} of them: "
                "its int8 figures would not be comparable"
            )
    figures: dict[str, dict[str, float]] = {}
    cfg = None
    for k, (person, fold) in enumerate(runs.items()):
        log.info("int8 fold %d/%d: %s", k + 1, len(folds), person)
        fold_id = fold.info.run_id
        cfg = ExperimentConfig.model_validate(load_run_config(fold_id))
        setup_tracking(cfg.tracking.experiment)
        with tempfile.TemporaryDirectory() as tmp_dir:
            tmp = Path(tmp_dir)
            src = download_onnx(fold.data.tags["model_uri"], tmp_dir)
            calibration = model_calibration_windows(cfg, calibrate_on, data_dir, cache_dir, n_calibration)
            described = quantize_onnx(
                src, tmp / "int8.onnx", calibration, rnn, float_first_conv, f"{calibrate_on} training windows"
            )
            golden = Path(client.download_artifacts(fold_id, "export/golden.npz", tmp_dir))
            with np.load(golden) as z:
                parity = onnx_parity(tmp / "int8.onnx", dict(z))
            run_tags = {"task": cfg.task, "real_loso_held_out": person, "quantized_from": fold_id}
            with mlflow.start_run(run_name=f"{cfg.name} int8 · held out {person}", tags=run_tags):
                mlflow.log_params({"quantization": described[:500], "quantized_from": fold_id})
                mlflow.log_metric("int8_golden_max_abs_diff", parity)
                mlflow.log_text(mlflow.artifacts.load_text(f"runs:/{fold_id}/config.yaml"), "config.yaml")
                mlflow.log_artifact(str(golden), "export")  # the fold's golden pair: write_run checks against it
                log_real_evaluation(cfg, tmp / "int8.onnx", data_dir, tmp)
                info = mlflow.onnx.log_model(
                    onnx.load(str(tmp / "int8.onnx")), name="model", save_as_external_data=False
                )
                mlflow.set_tag("model_uri", info.model_uri)
                run_id = mlflow.active_run().info.run_id  # type: ignore[union-attr]
        figures[person] = fold_figures(run_id, persons[person])
    assert cfg is not None
    source_of = {person: persons[person][0].source for person in figures}
    summary_id, _ = log_real_loso_summary(
        cfg, figures, source_of, data_dir, f"{cfg.name}_real_loso_int8", {"quantized_from": summary}
    )
    return summary_id
