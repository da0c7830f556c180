"""The live pose worker's cost per batch, in-process, side by side in one run: ``process_live`` over S sessions of
the served six-sensor streaming model (declared calibration, random readings, ``--frames`` frames each), as
sessions run plain, with the pelvis's heading from the legs (``pelvis_heading: legs``), and with one more sensor
than the model reads (``measured``: a left upper arm), and with the knees, elbows and hands answered as the network
gives them (``no_hinges``: what the knee hinges, the elbows' plane and the neutral wrists cost). The variants are
interleaved round by round so that the machine's drift falls on all of them alike; the median per variant is
reported.

    python -m benchmarks.bench_pose_batch                 -> benchmarks/results/pose_batch.json
    python -m benchmarks.bench_pose_batch --sessions 50 150 --rounds 40
"""

from __future__ import annotations

import argparse
import json
import platform
import time
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from benchmarks.machine import machine_state
from benchmarks.servers import REPO
from service.inference.pose import LivePose, PoseModel, process_live
from service.inference.registry import load_models, newest_version_dir

RESULTS = REPO / "benchmarks" / "results"
MODEL = "pose_full6_stream"
VARIANTS = {
    "plain": {},
    "legs": {"pelvis_heading": "legs"},
    "measured": {"measured": ["LeftUpperArm"]},
    "no_hinges": {},  # knees, elbows and hands as the network gives them, as before they were constrained (the cost)
}


class _NoHingeJoints(PoseModel):
    hinge_joints = False


def sessions(model: PoseModel, n: int, variant: str) -> list[LivePose]:
    extra = len(VARIANTS[variant].get("measured", []))
    if variant == "no_hinges":
        model = _NoHingeJoints(model.loaded)
    return [
        LivePose(
            model,
            "declared",
            Rotation.random(6 + extra, random_state=k).as_quat(scalar_first=True),
            **VARIANTS[variant],
        )
        for k in range(n)
    ]


def readings(rng: np.random.Generator, frames: int, sensors: int) -> np.ndarray:
    q = Rotation.random(frames * sensors, random_state=int(rng.integers(1 << 30))).as_quat(scalar_first=True)
    acc = rng.normal(scale=3.0, size=(frames, sensors, 3)) + [0.0, 0.0, 9.81]
    return np.concatenate([acc, rng.normal(size=(frames, sensors, 3)), q.reshape(frames, sensors, 4)], axis=2)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--sessions", type=int, nargs="+", default=[50, 150])
    parser.add_argument("--frames", type=int, default=4, help="frames per session per batch (a 4-sample packet)")
    parser.add_argument("--rounds", type=int, default=30, help="interleaved rounds; the median is reported")
    parser.add_argument("--out", type=Path, default=RESULTS / "pose_batch.json")
    args = parser.parse_args()
    start_state = machine_state(REPO / "onnx_models", "start")  # how fast the machine ran (benchmarks/machine.py)
    loaded = load_models(REPO / "onnx_models", 1)
    model = PoseModel(loaded[MODEL])
    rng = np.random.default_rng(0)
    live = {(v, n): sessions(model, n, v) for v in VARIANTS for n in args.sessions}
    batches = {
        key: [[readings(rng, args.frames, len(s.segments)) for s in ss] for _ in range(4)] for key, ss in live.items()
    }
    times: dict[tuple[str, int], list[float]] = {key: [] for key in live}
    for r in range(args.rounds + 2):
        for key, ss in live.items():
            batch = batches[key][r % 4]
            start = time.perf_counter()
            process_live([(s, f, 0) for s, f in zip(ss, batch, strict=True)])
            if r >= 2:  # the first rounds warm up
                times[key].append(time.perf_counter() - start)
        print(f"round {r + 1}/{args.rounds + 2}", flush=True)
    rows = []
    for (variant, n), t in times.items():
        ms = 1e3 * float(np.median(t))
        rows.append({"variant": variant, "sessions": n, "frames": args.frames, "median_ms": round(ms, 3)})
        print(f"{variant:>9}  {n:4d} sessions x {args.frames} frames  {ms:7.2f} ms per batch")
    out = {
        "model": f"{MODEL} {newest_version_dir(REPO / 'onnx_models', MODEL).name}",
        "machine": platform.platform(),
        "time": time.strftime("%Y-%m-%d %H:%M"),
        "results": rows,
        "machine_state": [start_state, machine_state(REPO / "onnx_models", "end")],
    }
    args.out.write_text(json.dumps(out, indent=1) + "\n")
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
