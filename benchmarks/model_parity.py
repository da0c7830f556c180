"""How far two shipped I2S files of one task answer apart, on every window of every real recording in the data
directory (each sensor's windows at the served hop, in the service's chunks of 8): the check that a file rebuilt
from the same weights (a cheaper graph, another quantisation) answers as the one it replaces.

python -m benchmarks.model_parity i2s_alignment/3.11.0 i2s_alignment/3.17.0 --out /tmp/parity.json

Alignment: the angle between the two answers of each window and segment hypothesis (all seven). Assignment: the
largest change of a class probability, and the share of windows whose most likely segment changes.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from benchmarks.bench_models import find
from service.core.manifest import read_manifest
from service.core.recordings import read_all_real
from service.core.rotations import geodesic_angle_deg
from service.core.windowing import sliding_windows
from service.inference.registry import load_model
from training.data.catalog import resolve_data_dir

CHUNK = 8  # windows per onnxruntime call, as the service batches them


def answers(model_dir: Path, windows: np.ndarray) -> np.ndarray:
    model = load_model(model_dir, threads=2)
    return np.concatenate([model.run(windows[i : i + CHUNK]) for i in range(0, len(windows), CHUNK)]).astype(np.float64)


def alignment_parity(a: np.ndarray, b: np.ndarray) -> dict[str, float]:
    """Angles between the unit quaternions ``(n, 7, 4)`` of the two files."""
    deg = geodesic_angle_deg(a.reshape(-1, 4), b.reshape(-1, 4))
    return {
        "answers": int(deg.size),
        "max_deg": float(deg.max()),
        "p9999_deg": float(np.quantile(deg, 0.9999)),
        "mean_deg": float(deg.mean()),
        **{f"over_{t}_deg": int((deg > t).sum()) for t in (0.01, 0.1, 1.0)},
    }


def assignment_parity(a: np.ndarray, b: np.ndarray) -> dict[str, float]:
    return {
        "windows": len(a),
        "max_probability_diff": float(np.abs(a - b).max()),
        "segment_changed_share": float((a.argmax(-1) != b.argmax(-1)).mean()),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("models", nargs=2, help="<name>/<version> of two shipped or archived files of one task")
    parser.add_argument("--data-dir", type=Path, default=None, help="default: WEARMOCAP_DATA_DIR")
    parser.add_argument("--out", type=Path, required=True)
    args = parser.parse_args()
    dirs = [find(m) for m in args.models]
    tasks = {read_manifest(d / "manifest.json").task for d in dirs}
    if len(tasks) != 1 or not tasks <= {"i2s_alignment", "i2s_assignment"}:
        raise SystemExit(f"two files of one I2S task, got {sorted(tasks)}")
    recordings = read_all_real(resolve_data_dir(args.data_dir))
    windows = np.concatenate([sliding_windows(s.imu) for r in recordings for s in r.sensors]).astype(np.float32)
    print(f"{len(windows)} windows of {len(recordings)} recordings", flush=True)
    a, b = (answers(d, windows) for d in dirs)
    parity = alignment_parity(a, b) if tasks == {"i2s_alignment"} else assignment_parity(a, b)
    print(json.dumps(parity, indent=1))
    result = {"command": "python -m benchmarks.model_parity " + " ".join(args.models), "models": args.models}
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps({**result, "recordings": len(recordings), **parity}, indent=1) + "\n")


if __name__ == "__main__":
    main()
