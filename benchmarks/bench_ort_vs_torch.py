"""onnxruntime vs torch eager on the same shipped weights and the same batches, in one run:
torch eager, onnxruntime on the float32 file, onnxruntime on the int8 file (``training.i2s.quantize``);
then the service's way of running both models (``service.inference.runner``) against one call per model
with two intra-op threads.

python -m benchmarks.bench_ort_vs_torch        -> benchmarks/results/ort_vs_torch.json
"""

from __future__ import annotations

import json
import tempfile
import time
from pathlib import Path

import mlflow
import numpy as np
import onnxruntime as ort
import torch

from benchmarks.servers import REPO
from service.core.manifest import read_manifest
from service.inference.registry import load_model
from service.inference.runner import ModelRunner
from training.i2s.config import ExperimentConfig
from training.i2s.export import export_module
from training.i2s.ship import load_run_config
from training.i2s.train import build_model
from training.i2s.warmstart import warm_start_from_shipped


def _time(fn, x: np.ndarray, repeats: int) -> float:
    fn(x)
    t = time.perf_counter()
    for _ in range(repeats):
        fn(x)
    return (time.perf_counter() - t) / repeats


def _torch_weights(run_id: str, model_dir: Path, net: torch.nn.Module) -> dict:
    """The run's checkpoint; runs logged before checkpoints existed: rebuilt from the ONNX file (verified)."""
    with tempfile.TemporaryDirectory() as tmp:
        try:
            path = mlflow.artifacts.download_artifacts(f"runs:/{run_id}/checkpoint/model_state.pt", dst_path=tmp)
            return torch.load(path, weights_only=True)
        except mlflow.exceptions.MlflowException:
            return warm_start_from_shipped(model_dir, net)


def _shipped(task: str) -> tuple[Path, Path]:
    """(float32 dir, int8 dir) of the newest shipped int8 version and the version it was quantised from."""
    dirs = {p.parent: read_manifest(p) for p in (REPO / "onnx_models" / task).glob("*/manifest.json")}
    int8 = max((d for d, m in dirs.items() if "quantization" in m.exporter), key=lambda d: dirs[d].version)
    return int8.parent / str(dirs[int8].exporter["quantized_from"]), int8


def _session(model_dir: Path, threads: int) -> ort.InferenceSession:
    """The service's session setup (manifest-checked, no busy-waiting) with ``threads`` intra-op threads."""
    return load_model(model_dir, threads).session


def main() -> None:
    torch.set_num_threads(2)
    mlflow.set_tracking_uri(f"sqlite:///{REPO / 'mlflow.db'}")
    out: dict = {"command": "python -m benchmarks.bench_ort_vs_torch", "threads": 2}
    int8_dirs = {}
    for task in ("i2s_assignment", "i2s_alignment"):
        fp32_dir, int8_dirs[task] = _shipped(task)
        manifest = read_manifest(fp32_dir / "manifest.json")
        cfg = ExperimentConfig.model_validate(load_run_config(manifest.mlflow["run_id"]))
        net = build_model(cfg)
        net.load_state_dict(_torch_weights(manifest.mlflow["run_id"], fp32_dir, net))
        module = export_module(net)
        fp32, int8 = _session(fp32_dir, 2), _session(int8_dirs[task], 2)
        for batch in (1, 256):
            x = np.random.default_rng(0).normal(size=(batch, 128, 6)).astype(np.float32)
            repeats = 200 if batch == 1 else 10
            with torch.inference_mode():
                t_torch = _time(lambda a, m=module: m(torch.from_numpy(a)), x, repeats)
            t_fp32 = _time(lambda a, s=fp32: s.run(None, {"imu": a}), x, repeats)
            t_int8 = _time(lambda a, s=int8: s.run(None, {"imu": a}), x, repeats)
            out[f"{task}_batch{batch}"] = {
                "files": {"float32": str(fp32_dir.relative_to(REPO)), "int8": str(int8_dirs[task].relative_to(REPO))},
                "torch_eager_windows_per_s": batch / t_torch,
                "onnxruntime_float32_windows_per_s": batch / t_fp32,
                "onnxruntime_int8_windows_per_s": batch / t_int8,
                "ratio_ort_float32_over_torch": t_torch / t_fp32,
                "ratio_ort_int8_over_torch": t_torch / t_int8,
            }
            print(task, batch, out[f"{task}_batch{batch}"])
    out["both_models_int8"] = _runner_comparison(int8_dirs)
    print(out["both_models_int8"])
    (REPO / "benchmarks" / "results").mkdir(parents=True, exist_ok=True)
    (REPO / "benchmarks" / "results" / "ort_vs_torch.json").write_text(json.dumps(out, indent=2) + "\n")


def _runner_comparison(int8_dirs: dict[str, Path]) -> dict:
    """Assignment + alignment per window: one call per model with 2 intra-op threads vs the service runner."""
    two_threads = {task: _session(d, 2) for task, d in int8_dirs.items()}
    single = {task: load_model(d, threads=1) for task, d in int8_dirs.items()}
    result = {}
    for batch in (1, 256):
        x = np.random.default_rng(1).normal(size=(batch, 128, 6)).astype(np.float32)
        repeats = 200 if batch == 1 else 10
        t_serial = _time(lambda a: [s.run(None, {"imu": a}) for s in two_threads.values()], x, repeats)
        row = {"one_call_per_model_2_threads_ms": t_serial * 1000}
        for chunk in (8, 16, 64):
            runner = ModelRunner(single, threads=2, chunk=chunk)
            row[f"runner_2x1_threads_chunk{chunk}_ms"] = _time(runner, x, repeats) * 1000
            runner.close()
        row["windows_per_s_best"] = batch / (min(row.values()) / 1000)
        result[f"batch{batch}"] = row
    return result


if __name__ == "__main__":
    main()
