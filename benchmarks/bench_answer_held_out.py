"""Time to answer on live streams, of people the answering model never saw: each real walking recording of the data
directory streamed at real time to a service that serves the fold of a ``real-loso`` run that held its person out
(with the confidence calibration fitted without that person, and the served alignment), one session with all its
labelled sensors. Per recording: the seconds (stream time) from the first moving window until the joint assignment
is right and stays right, and until the status is ``assigned``; median and worst over the walks. Beside each, the
same figure replayed offline from the same fold's predictions over the same seconds
(``training.i2s.calibration.time_to_answer``): where the two differ by more than the live messages' spacing (an
``assignment`` every 0.5 s of stream time, ``WEARMOCAP_STREAM_ASSIGNMENT_INTERVAL_S``, which also hides brief wrong
answers between them), the service does not answer as the replay says it does.

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
from benchmarks.servers import served_dir, start_service, stop
from service.core.assignment import ConfidenceModel
from service.core.manifest import read_manifest, write_manifest
from service.core.recordings import RealRecording, read_all_real
from service.core.windowing import HOP_SAMPLES, MODEL_RATE_HZ, WINDOW_SAMPLES
from training.data.catalog import resolve_data_dir
from training.i2s.calibration import (
    HeldOut,
    confidence_spec,
    fold_predictions,
    nested,
    servable,
    sessions,
    time_to_answer,
    with_swing,
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
    return served_dir("i2s_alignment")


def fold_services(
    summary_run_id: str, people: list[str], calibrations: dict[str, ConfidenceModel], root: Path
) -> dict[str, Path]:
    """Per held-out person a models folder: the fold's assignment file, whose manifest carries the confidence
    calibration fitted on the other people's sessions only (``nested``), and the served alignment."""
    alignment = served_alignment()
    folds = fold_runs(summary_run_id)
    out = {}
    for person in people:
        models = root / person
        written = write_run(folds[person], root / "written" / person, version="0.0.0")
        model_dir = models / "i2s_assignment" / "0.0.0"  # whatever the config's registered name was
        model_dir.parent.mkdir(parents=True)
        shutil.move(written, model_dir)
        manifest = read_manifest(model_dir / "manifest.json")
        if manifest.task != "i2s_assignment":
            raise SystemExit(f"fold run {folds[person]} is a {manifest.task} model, not an assignment one")
        manifest.confidence = confidence_spec(
            calibrations[person],
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
    n = max(0, (int(seconds * MODEL_RATE_HZ) - WINDOW_SAMPLES) // HOP_SAMPLES + 1)
    return [
        replace(
            h,
            sensors=[replace(s, log_probs=s.log_probs[:n], moving=s.moving[:n]) for s in h.sensors],
            swing=None if h.swing is None else h.swing[:n],
        )
        for h in held_out
    ]


async def stream_people(bases: dict[str, str], recordings: list[RealRecording], seconds: float) -> list[dict]:
    """Every recording streamed at real time to its person's service, all at once."""
    runs = [answer_session(bases[r.subject].replace("http", "ws") + "/v1/stream", r, seconds, 0.0) for r in recordings]
    return await asyncio.gather(*runs)


def _finite(value: float | None) -> float | None:
    """A time in seconds, or None for never (the live column says None, the replay NaN)."""
    return None if value is None or not np.isfinite(value) else float(value)


def _summary(values: list[float | None]) -> dict[str, float | int]:
    got = [v for v in values if v is not None]
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
    predicted = with_swing(fold_predictions(args.loso_run, data_dir), data_dir)  # as the service weighs it
    # the calibration as ``calibrate`` fits it (sessions of every recording), one per person without that person;
    # the replay judges by what the service is given (``servable``)
    calibrations = {p: servable(m) for p, m in nested(sessions(predicted))[1].items()}
    held_out = [h for h in predicted if h.activity.startswith(WALKING)]
    replayed = time_to_answer(truncated(held_out, args.seconds), calibrations)
    names = {h.recording for h in held_out}
    walking = [r for r in read_all_real(data_dir) if r.name in names]
    people = sorted({r.subject for r in walking})
    per: dict[str, dict] = {}
    with tempfile.TemporaryDirectory() as tmp:
        folders = fold_services(args.loso_run, people, calibrations, Path(tmp))
        for first in range(0, len(people), args.servers):
            group = people[first : first + args.servers]
            started = {p: start_service(folders[p], threads=1) for p in group}
            try:
                chosen = [r for r in walking if r.subject in group]
                bases = {p: base for p, (_, base) in started.items()}
                lives = asyncio.run(stream_people(bases, chosen, args.seconds))
                for recording, live in zip(chosen, lives, strict=True):
                    replay = replayed.get(recording.name, {"no_moving_window": True})
                    per[recording.name] = {"person": recording.subject, "live": live, "replay": replay}
                    print(recording.name, json.dumps(live), flush=True)
            finally:
                for proc, _ in started.values():
                    stop(proc)
    # both columns over the recordings streamed to the end with a moving window in both
    both = [v for v in per.values() if "right_s" in v["live"] and "right_s" in v["replay"]]
    live_right = [_finite(v["live"]["right_s"]) for v in both]
    replay_right = [_finite(v["replay"]["right_s"]) for v in both]
    pairs = list(zip(live_right, replay_right, strict=True))
    differ = [abs(a - b) for a, b in pairs if a is not None and b is not None]
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
        "no_moving_window": sum("no_moving_window" in {*v["live"], *v["replay"]} for v in per.values()),
        "compared": len(both),
        "seconds_streamed_per_recording": args.seconds,
        "live_right_for_good": _summary(live_right),
        "live_assigned": _summary([_finite(v["live"]["committed_s"]) for v in both]),
        "live_assigned_wrong": sum(v["live"]["committed_right"] is False for v in both),
        "replay_right_for_good": _summary(replay_right),
        "replay_assigned": _summary([_finite(v["replay"]["committed_s"]) for v in both]),
        "replay_assigned_wrong": sum(v["replay"]["committed_right"] == 0.0 for v in both),
        "live_vs_replay_right_for_good_abs_diff_s_max": max(differ, default=0.0),
        "live_vs_replay_one_never_right_for_good": sum((a is None) != (b is None) for a, b in pairs),
        "per_recording": per,
    }
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(result, indent=2) + "\n")
    print(json.dumps({k: v for k, v in result.items() if k != "per_recording"}, indent=2))


if __name__ == "__main__":
    main()
