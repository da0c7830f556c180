"""The design set of the body's translation rule (``service.core.translation``): training-side clips only.

The rule has three constants (the flight threshold, the contact band, the inertial share). They were chosen on
clips of the people a pose model trains on, never on the validation or held-out people: per activity, a fixed
random draw of clips (seed 0), the model's own answer on one simulated session per clip (seed 7), and the rule on
the true pose beside it. ``python -m training.cli pose-translation-design`` prints the table docs/pose.md quotes;
its options run the rule with other constants.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from service.inference.pose import PoseModel
from service.inference.registry import load_model
from training.pose.config import PoseConfig
from training.pose.data import MotionClip
from training.pose.evaluate import evaluate_clips
from training.pose.train import fixed_sessions

DESIGN_SEED = 7
# (activity, clips drawn, frames: more than, at most); "run" twice: Bandai-Namco's long runs (most at 1.4 m/s,
# little flight) and its short ones (most at 2.5-4 m/s, as fast as the held-out runs)
DESIGN_SETS = (
    ("walk", 6, 400, None),
    ("walk_turn", 6, 400, None),
    ("walk_backward", 6, 400, None),
    ("run", 6, 400, None),
    ("run", 12, 120, 400),
    ("jump", 6, 400, None),
    ("wave", 6, 400, None),
)


def _mean(values: list[float]) -> float:
    finite = [v for v in values if np.isfinite(v)]
    return float(np.mean(finite)) if finite else float("nan")


def design_clips(train: list[MotionClip]) -> list[tuple[str, list[MotionClip]]]:
    """Per design set, its clips: a fixed draw from the training side's clips of that activity and length."""
    rng = np.random.default_rng(0)
    out = []
    for activity, count, shortest, longest in DESIGN_SETS:
        pool = [
            c
            for c in train
            if c.activity == activity and shortest < c.motion.n_frames <= (longest or c.motion.n_frames)
        ]
        picked = [pool[k] for k in rng.permutation(len(pool))[:count]]
        frames = f"> {shortest}" if longest is None else f"{shortest + 1}-{longest}"
        out.append((f"{activity} ({frames} frames)", picked))
    return out


def design_table(model_dir: Path, train: list[MotionClip]) -> dict[str, dict[str, float]]:
    """Per design set, the mean ``trans_*`` metrics of ``training.pose.evaluate`` with the model's answer."""
    model = PoseModel(load_model(model_dir, 2))
    cfg = PoseConfig(name=model.name, sensors=model.spec.sensors, output_segments=model.spec.output_segments)
    table = {}
    for name, clips in design_clips(train):
        sessions = fixed_sessions(clips, cfg, DESIGN_SEED)
        results = evaluate_clips(model.predict, clips, sessions, cfg.sensors, cfg.outputs, hinges=model.hinge_joints)
        keys = [k for k in results[0].metrics if k.startswith("trans_")] if results else []
        table[name] = {k: _mean([r.metrics[k] for r in results]) for k in keys} | {"clips": float(len(clips))}
    return table
