"""onnxruntime vs torch eager on the same shipped model and the same batches, in one run.

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
from training.config import ExperimentConfig
from training.export import export_module
from training.ship import _load_config
from training.train import build_model
from training.warmstart import warm_start_from_shipped


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


def main() -> None:
    torch.set_num_threads(2)
    mlflow.set_tracking_uri(f"sqlite:///{REPO / 'mlflow.db'}")
    out = {"command": "python -m benchmarks.bench_ort_vs_torch", "threads": 2}
    for task in ("i2s_assignment", "i2s_alignment"):
        model_dir = sorted(p.parent for p in (REPO / "onnx_models" / task).glob("*/manifest.json"))[-1]
        manifest = read_manifest(model_dir / "manifest.json")
        cfg = ExperimentConfig.model_validate(_load_config(manifest.mlflow["run_id"]))
        net = build_model(cfg)
        net.load_state_dict(_torch_weights(manifest.mlflow["run_id"], model_dir, net))
        module = export_module(net)
        options = ort.SessionOptions()
        options.intra_op_num_threads = 2
        session = ort.InferenceSession(str(model_dir / "model.onnx"), options, providers=["CPUExecutionProvider"])
        for batch in (1, 256):
            x = np.random.default_rng(0).normal(size=(batch, 128, 6)).astype(np.float32)
            repeats = 200 if batch == 1 else 10
            with torch.inference_mode():
                t_torch = _time(lambda a, m=module: m(torch.from_numpy(a)), x, repeats)
            t_ort = _time(lambda a, s=session: s.run(None, {"imu": a}), x, repeats)
            out[f"{task}_batch{batch}"] = {
                "torch_eager_windows_per_s": batch / t_torch,
                "onnxruntime_windows_per_s": batch / t_ort,
                "ratio_ort_over_torch": t_torch / t_ort,
            }
            print(task, batch, out[f"{task}_batch{batch}"])
    (REPO / "benchmarks" / "results").mkdir(parents=True, exist_ok=True)
    (REPO / "benchmarks" / "results" / "ort_vs_torch.json").write_text(json.dumps(out, indent=2) + "\n")


if __name__ == "__main__":
    main()
