"""Per-window cost of shipped model files side by side, in one run: each file loaded as the service loads it
(``service.inference.registry.load_model``, one intra-op thread, no spinning), the same random windows, the
files interleaved round by round so that the machine's drift falls on all of them alike.

python -m benchmarks.bench_models                      -> benchmarks/results/models.json
python -m benchmarks.bench_models i2s_alignment/3.5.0 i2s_alignment/3.7.0 --out /tmp/x.json

Files that are no longer served are found in the archive (``mlflow_snapshot/models``) as well.
"""

from __future__ import annotations

import argparse
import json
import platform
import time
from pathlib import Path

import numpy as np

from benchmarks.servers import REPO
from service.inference.registry import load_model

RESULTS = REPO / "benchmarks" / "results"
ROOTS = (REPO / "onnx_models", REPO / "mlflow_snapshot" / "models")
DEFAULT = ["i2s_alignment/3.11.0", "i2s_alignment/3.17.0", "i2s_assignment/1.12.0"]


def find(name_version: str) -> Path:
    for root in ROOTS:
        if (root / name_version / "manifest.json").is_file():
            return root / name_version
    raise SystemExit(f"{name_version}: no shipped or archived model of that name and version under {ROOTS}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("models", nargs="*", default=DEFAULT, help="<name>/<version> of shipped or archived files")
    parser.add_argument("--batches", type=int, nargs="+", default=[1, 8, 32, 256])
    parser.add_argument("--rounds", type=int, default=7, help="interleaved rounds; the median is reported")
    parser.add_argument("--seconds", type=float, default=0.3, help="time per file, batch size and round")
    parser.add_argument("--out", type=Path, default=RESULTS / "models.json")
    args = parser.parse_args()
    loaded = {m: load_model(find(m), threads=1) for m in args.models}
    for m, model in loaded.items():
        if len(model.manifest.inputs) != 1 or model.manifest.inputs[0].shape[0] != "batch":
            raise SystemExit(
                f"{m} takes {len(model.manifest.inputs)} inputs or a fixed batch; this bench times "
                "single-input windowed models (the I2S and flex files)"
            )
    shapes = {m: model.manifest.inputs[0].shape[1:] for m, model in loaded.items()}
    rng = np.random.default_rng(0)
    inputs = {(m, b): rng.standard_normal((b, *shapes[m])).astype(np.float32) for m in loaded for b in args.batches}
    times: dict[tuple[str, int], list[float]] = {key: [] for key in inputs}
    for r in range(args.rounds):
        for (m, b), x in inputs.items():
            run = loaded[m].run
            run(x)
            n, start = 0, time.perf_counter()
            while (elapsed := time.perf_counter() - start) < args.seconds or n < 3:
                run(x)
                n += 1
            times[(m, b)].append(elapsed / n)
        print(f"round {r + 1}/{args.rounds}", flush=True)
    rows = [
        {
            "model": m,
            "batch": b,
            "ms_per_call": round(1e3 * float(np.median(times[(m, b)])), 3),
            "ms_per_window": round(1e3 * float(np.median(times[(m, b)])) / b, 4),
        }
        for (m, b) in inputs
    ]
    for row in rows:
        print(f"{row['model']:>24}  batch {row['batch']:>4}  {row['ms_per_window']:.3f} ms/window")
    result = {
        "command": "python -m benchmarks.bench_models " + " ".join(args.models),
        "machine": {"cpus": __import__("os").cpu_count(), "python": platform.python_version()},
        "threads": 1,
        "rounds": args.rounds,
        "results": rows,
    }
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(result, indent=2) + "\n")


if __name__ == "__main__":
    main()
