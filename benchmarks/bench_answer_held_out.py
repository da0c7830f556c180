"""Time to answer on live streams, of people the answering model never saw: each real walking recording of the data
directory streamed at real time to a service that serves the fold of a ``real-loso`` run that held its person out
(with the confidence calibration fitted without that person, and the served alignment), one session with all its
labelled sensors. Per recording: the seconds (stream time) from the first moving window until the joint assignment
is right and stays right, and until the status is ``assigned``; median and worst over the walks. Beside each, the
same figure replayed offline from the same fold's predictions over the same seconds
(``training.i2s.calibration.time_to_answer``): where the two differ, the service does not answer as the replay
says it does.

    python -m benchmarks.bench_answer_held_out --loso-run <real-loso summary run> [--seconds 45] [--servers 4]

The fold runs must hold their models (a ``real-loso`` run trained in this store; a restored snapshot keeps none).
Results: ``benchmarks/results/time_to_answer_held_out.json``.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import platform
import shutil
import tempfile
from dataclasses import replace
from pathlib import Path

import numpy as np
from mlflow.tracking import MlflowClient

from benchmarks.bench_service import RESULTS, answer_session
from benchmarks.servers import REPO, start_service, stop
from service.core.manifest import read_manifest, write_manifest
from service.core.recordings import RealRecording, read_all_real
from service.core.windowing import HOP_SAMPLES, MODEL_RATE_HZ, WINDOW_SAMPLES
from training.data.catalog import resolve_data_dir
from training.i2s.calibration import (
    HeldOut,
    confidence_spec,
    fold_predictions,
    nested,
    sessions,
    time_to_answer,
)
from training.i2s.ship import write_run
from training.snapshot import local_run_id
from training.tracking import setup_tracking

WALKING = ("walk", "stairs")  # as the service benchmark's time to answer and the calibration's replay


def fold_runs(summary_run_id: str) -> dict[str, str]:
    """Held-out person → fold run id of a ``real-loso`` summary run."""
    tags = MlflowClient().get_run(local_run_id(summary_run_id)).data.tags
    folds = {k.removeprefix("fold_run."): local_run_id(v) for k, v in tags.items() if k.startswith("fold_run.")}
    if not folds:
        raise SystemExit(f"run {summary_run_id} is not a real-loso summary run (no fold_run.* tags)")
    return folds


def served_alignment() -> Path:
    """The newest shipped alignment (what the service loads by default)."""
    versions = (REPO / "onnx_models" / "i2s_alignment").iterdir()
    return max(versions, key=lambda p: tuple(int(x) for x in p.name.split(".")))


def fold_services(summary_run_id: str, held_out: list[HeldOut], root: Path) -> dict[str, Path]:
    """Per held-out person a models folder: the fold's assignment file, whose manifest carries the confidence
    calibration fitted on the other people's sessions only (``nested``), and the served alignment."""
    _, per_person = nested(sessions(held_out))
    alignment = served_alignment()
    out = {}
    for person, run_id in sorted(fold_runs(summary_run_id).items()):
        models = root / person
        model_dir = write_run(run_id, models, version="0.0.0")
        manifest = read_manifest(model_dir / "manifest.json")
        manifest.confidence = confidence_spec(
            per_person[person],
            fitted_on=f"held-out sessions of real-loso run {summary_run_id} without {person}",
            metrics={},
            command=f"python -m benchmarks.bench_answer_held_out --loso-run {summary_run_id}",
        )
        write_manifest(manifest, model_dir / "manifest.json")
        shutil.copytree(alignment, models / "i2s_alignment" / alignment.name)
        out[person] = models
    return out


def truncated(held_out: list[HeldOut], seconds: float) -> list[HeldOut]:
    """The recordings' predictions over their first ``seconds``: the windows a stream of that length produces."""
    n = (int(seconds * MODEL_RATE_HZ) - WINDOW_SAMPLES) // HOP_SAMPLES + 1
    return [
        replace(h, sensors=[replace(s, log_probs=s.log_probs[:n], moving=s.moving[:n]) for s in h.sensors])
        for h in held_out
    ]


async def stream_people(bases: dict[str, str], recordings: list[RealRecording], seconds: float) -> list[dict]:
    """Every recording streamed at real time to its person's service, all at once."""
    runs = [answer_session(bases[r.subject].replace("http", "ws") + "/v1/stream", r, seconds, 0.0) for r in recordings]
    return await asyncio.gather(*runs)


def _summary(values: list[float | None]) -> dict[str, float | int]:
    got = [v for v in values if v is not None and np.isfinite(v)]
    return {
        "median_s": float(np.median(got)) if got else float("nan"),
        "worst_s": float(max(got)) if got else float("nan"),
        "never": len(values) - len(got),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--loso-run", required=True, help="a real-loso summary run whose fold runs hold their models")
    parser.add_argument("--seconds", type=float, default=45.0, help="seconds of each recording streamed")
    parser.add_argument("--servers", type=int, default=4, help="fold services running at once")
    parser.add_argument("--out", type=Path, default=RESULTS / "time_to_answer_held_out.json")
    args = parser.parse_args()
    setup_tracking("i2s")
    data_dir = resolve_data_dir(None)
    held_out = [h for h in fold_predictions(args.loso_run, data_dir) if h.activity.startswith(WALKING)]
    replayed = time_to_answer(truncated(held_out, args.seconds), nested(sessions(held_out))[1])
    names = {h.recording for h in held_out}
    walking = [r for r in read_all_real(data_dir) if r.name in names]
    per: dict[str, dict] = {}
    with tempfile.TemporaryDirectory() as tmp:
        folders = fold_services(args.loso_run, held_out, Path(tmp))
        people = sorted({r.subject for r in walking})
        for first in range(0, len(people), args.servers):
            group = people[first : first + args.servers]
            started = {p: start_service(folders[p], threads=1) for p in group}
            try:
                chosen = [r for r in walking if r.subject in group]
                bases = {p: base for p, (_, base) in started.items()}
                lives = asyncio.run(stream_people(bases, chosen, args.seconds))
                for recording, live in zip(chosen, lives, strict=True):
                    replay = replayed.get(recording.name, {})
                    per[recording.name] = {"person": recording.subject, "live": live, "replay": replay}
                    print(recording.name, json.dumps(live), flush=True)
            finally:
                for proc, _ in started.values():
                    stop(proc)
    ran = [v for v in per.values() if "right_s" in v["live"]]
    nan = float("nan")
    agreement = [
        abs(v["live"]["right_s"] - v["replay"]["right_s"])
        for v in ran
        if v["live"]["right_s"] is not None and np.isfinite(v["replay"].get("right_s", nan))
    ]
    result = {
        "command": f"python -m benchmarks.bench_answer_held_out --loso-run {args.loso_run} --seconds {args.seconds} "
        f"--servers {args.servers}",
        "what": "each walking recording streamed at real time to the fold model that never saw its person (with a "
        "confidence calibrated without that person and the served alignment); the replay column is the same "
        "fold's offline replay over the same seconds",
        "machine": {"cpus": __import__("os").cpu_count(), "python": platform.python_version()},
        "loso_run": args.loso_run,
        "alignment": served_alignment().name,
        "recordings": len(per),
        "refused": sum("refused" in v["live"] for v in per.values()),
        "seconds_streamed_per_recording": args.seconds,
        "live_right_for_good": _summary([v["live"]["right_s"] for v in ran]),
        "live_assigned": _summary([v["live"]["committed_s"] for v in ran]),
        "live_assigned_wrong": sum(v["live"]["committed_right"] is False for v in ran),
        "replay_right_for_good": _summary([v["replay"].get("right_s") for v in per.values()]),
        "replay_assigned": _summary([v["replay"].get("committed_s") for v in per.values()]),
        "live_vs_replay_right_for_good_abs_diff_s_max": max(agreement, default=nan),
        "per_recording": per,
    }
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(result, indent=2) + "\n")
    print(json.dumps({k: v for k, v in result.items() if k != "per_recording"}, indent=2))


if __name__ == "__main__":
    main()
