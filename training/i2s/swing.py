"""How the gyroscope norms of sensors worn together swing together, per pair of segments: the model that the
per-moment answer weighs (``service.core.assignment.SWING``), fitted on simulated walking, and what it does to
the held-out per-moment answers of a ``real-loso`` run; and the side evidence of the pelvis' sway
(``service.core.assignment.sway_table``), fitted on the real recordings that carry a pelvis sensor and evaluated
with each person held out (not weighed by the service: docs/models.md).

Per moving window of a clip and per pair of its seven segments, the Fisher z (atanh) of the Pearson correlation of
their gyroscope norms over the window; per pair type (``service.core.assignment.swing_pair_type``: the two body
parts, and whether they are on one leg, on both legs, or one is the pelvis) its mean and standard deviation. The
norm of the angular velocity does not depend on how a sensor is mounted, so the segment's own is the sensor's.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from pathlib import Path

import numpy as np

from service.core.assignment import (
    STILL_GYR_MEAN_RADS,
    SWING_PAIR_TYPES,
    gyro_norm,
    is_moving,
    pelvis_lateral,
    sway_z,
    swing_pair_type,
    swing_z,
)
from service.core.recordings import RealRecording
from service.core.segments import BODY_PART, SEGMENTS
from service.core.windowing import HOP_SAMPLES, WINDOW_SAMPLES, sliding_windows
from service.inference.predict import mean_alignment
from service.settings import Settings
from training.i2s.data.mocap import Clip
from training.i2s.evaluate import moving_per_moment, settled_alignments


def swing_samples(clips: list[Clip]) -> dict[str, np.ndarray]:
    """Per pair type, the z of every window of ``clips`` in which both segments move."""
    out: dict[str, list[float]] = {name: [] for name in SWING_PAIR_TYPES}
    n_segments = len(BODY_PART)
    pairs = [
        (a, b, SWING_PAIR_TYPES[swing_pair_type(a, b)]) for a in range(n_segments) for b in range(a + 1, n_segments)
    ]
    for clip in clips:
        norms = np.linalg.norm(clip.kin.gyr_rads, axis=-1)  # (T, 7)
        for start in range(0, clip.n_samples - WINDOW_SAMPLES + 1, HOP_SAMPLES):
            window = norms[start : start + WINDOW_SAMPLES].T
            moving = window.mean(axis=1) > STILL_GYR_MEAN_RADS
            z = swing_z(window)
            for a, b, name in pairs:
                if moving[a] and moving[b]:
                    out[name].append(z[a, b])
    return {name: np.asarray(v) for name, v in out.items()}


def fit_swing(clips: list[Clip]) -> dict[str, tuple[float, float, int]]:
    """Per pair type: (mean z, standard deviation of z, number of windows)."""
    return {name: (float(z.mean()), float(z.std()), len(z)) for name, z in swing_samples(clips).items() if len(z)}


def recording_laterals(
    rec: RealRecording, align: Callable[[np.ndarray], np.ndarray], live: bool = True
) -> list[np.ndarray]:
    """Per labelled sensor of ``rec``, its windows' ``pelvis_lateral`` ``(N, T)``, the pelvis hypothesis being the
    sensor's settled alignment (``mean_alignment`` of the alignment model's pelvis row over its moving windows, at
    most the service's ``stream_alignment_windows`` of them): with ``live``, as a stream knows it after each window
    (NaN before the sensor has moved); else over the whole recording. ``align``: windows ``(B, T, 6)`` →
    q_segment_imu ``(B, 7, 4)``."""
    capacity = Settings().stream_alignment_windows
    out = []
    for sensor in (s for s in rec.sensors if s.segment is not None):
        windows = sliding_windows(sensor.imu.astype(np.float32))
        quats = np.concatenate([align(windows[i : i + 512]) for i in range(0, len(windows), 512)])
        pelvis, moving = quats[:, SEGMENTS.index("Pelvis")], is_moving(windows)
        if not live:
            out.append(pelvis_lateral(windows, mean_alignment(pelvis[moving] if moving.any() else pelvis)[0]))
            continue
        settled = settled_alignments(pelvis[moving], capacity)  # after each moving window
        latest = np.cumsum(moving) - 1  # the latest moving window at or before each window (-1: none yet)
        lateral = np.full(windows.shape[:2], np.nan)
        for i in np.flatnonzero(latest >= 0):
            lateral[i] = pelvis_lateral(windows[i : i + 1], settled[latest[i]])[0]
        out.append(lateral)
    return out


def sway_samples(rec: RealRecording, laterals: list[np.ndarray]) -> dict[str, np.ndarray]:
    """Per leg class of ``rec``'s labelled sensors, the ``sway_z`` of its windows against the pelvis sensor's, at
    the moments both move; empty without a labelled pelvis sensor."""
    sensors = [s for s in rec.sensors if s.segment is not None]
    segments = [s.segment for s in sensors]
    if SEGMENTS.index("Pelvis") not in segments:
        return {}
    p = segments.index(SEGMENTS.index("Pelvis"))
    windows = [sliding_windows(s.imu.astype(np.float32)) for s in sensors]
    n = min(len(w) for w in windows)
    out = {}
    for k, w in enumerate(windows):
        if k == p:
            continue
        both = is_moving(w[:n]) & is_moving(windows[p][:n])
        out[SEGMENTS[segments[k]]] = sway_z(laterals[p][:n][both], gyro_norm(w[:n][both])[:, None])[:, 0]
    return out


def fit_sway(samples: Sequence[dict[str, np.ndarray]]) -> dict[str, tuple[float, float, int]]:
    """Per leg class: (mean z, standard deviation of z, number of windows) over ``samples`` (``sway_samples``)."""
    pooled: dict[str, list[np.ndarray]] = {}
    for sample in samples:
        for name, z in sample.items():
            pooled.setdefault(name, []).append(z)
    return {
        name: (float(np.concatenate(zs).mean()), float(np.concatenate(zs).std()), sum(len(z) for z in zs))
        for name, zs in pooled.items()
    }


SWING_LOSO = "real_leave_one_person_out_swing"


SWAY_WEIGHTS = (0.0625, 0.125, 0.25, 0.5, 1.0)  # the weights the table compares by default


def swing_table(
    summary_run_id: str,
    data_dir: Path,
    weights: Sequence[float] = (),
    model_dir: Path | None = None,
    command: str = "",
    sway_weights: Sequence[float] = SWAY_WEIGHTS,
    live: bool = True,
) -> str:
    """A markdown table: per held-out person, per source and pooled, the per-moment answers of a ``real-loso`` run's
    folds (moving windows, as ``training.i2s.evaluate.evaluate_real`` scores them) without and with how the sensors
    swing together, and for each of ``weights`` the same with that ``SWING_WEIGHT`` (a comparison of weights); then,
    for each of ``sway_weights``, with the pelvis' sway too (``service.core.assignment.sway_table``, fitted on every
    person but the held-out one; the pelvis' frame from the served alignment model as a stream knows it, or with
    ``live`` false over the whole recording). With ``model_dir`` (a model of that recipe) its manifest gets the
    figures with ``SWING_WEIGHT`` as the evaluation ``SWING_LOSO``."""
    from service.core.assignment import SWING_WEIGHT, sway_table
    from service.core.recordings import read_all_real
    from service.inference.registry import load_models
    from training.i2s.calibration import fold_predictions

    part = np.array(BODY_PART + ("unassigned",))
    columns = [None, SWING_WEIGHT, *weights]
    recordings = {r.name: r for r in read_all_real(data_dir)}
    held_out = fold_predictions(summary_run_id, data_dir)
    align = load_models(Path("onnx_models"), 2)["i2s_alignment"].run
    laterals = {h.recording: recording_laterals(recordings[h.recording], align, live) for h in held_out}
    samples = {h.recording: (h.person, sway_samples(recordings[h.recording], laterals[h.recording])) for h in held_out}
    sums: dict[str, np.ndarray] = {}
    for held in held_out:
        sensors = [s for s in recordings[held.recording].sensors if s.segment is not None]
        norms = [gyro_norm(sliding_windows(s.imu.astype(np.float32))) for s in sensors]
        log_probs, moving = [p.log_probs for p in held.sensors], [p.moving for p in held.sensors]
        truth = np.concatenate([np.full(int(m.sum()), p.segment) for p, m in zip(held.sensors, moving, strict=True)])
        others = fit_sway([z for person, z in samples.values() if person != held.person])
        table = sway_table({name: (mean, std) for name, (mean, std, _) in others.items()})
        row = [len(truth)]
        for weight in columns:  # scored as evaluate_real scores them
            swing = {} if weight is None else {"gyro_norms": norms, "swing_weight": weight}
            got = np.concatenate(moving_per_moment(log_probs, moving, **swing))
            row += [(got == truth).sum(), (part[got] == part[truth]).sum()]
        for weight in sway_weights:
            sway = {"laterals": laterals[held.recording], "sway": table, "sway_weight": weight}
            got = np.concatenate(moving_per_moment(log_probs, moving, gyro_norms=norms, **sway))
            row += [(got == truth).sum(), (part[got] == part[truth]).sum()]
        for group in (held.person, f"pooled/{held.recording.split('/')[0]}", "pooled"):
            sums[group] = sums.get(group, 0) + np.array(row, dtype=np.float64)
    if model_dir is not None:
        _record(model_dir, summary_run_id, sums, command)
    names = ["per moment", f"swinging together ({SWING_WEIGHT:g})"] + [f"weight {w:g}" for w in weights]
    frame = "live" if live else "whole recording"
    names += [f"and the pelvis' sway ({frame}) {w:g}" for w in sway_weights]
    lines = ["| held out (moving windows) | " + " | ".join(f"{n}: right / ignoring side" for n in names) + " |"]
    lines.append("|" + " --- |" * (1 + len(names)))
    for group in sorted(sums, key=lambda g: (g.startswith("pooled"), g)):
        total = sums[group]
        cells = [
            f"{100 * total[1 + 2 * c] / total[0]:.2f} / {100 * total[2 + 2 * c] / total[0]:.2f} %"
            for c in range(len(names))
        ]
        lines.append(f"| {group} ({int(total[0])}) | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def _record(model_dir: Path, summary_run_id: str, sums: dict[str, np.ndarray], command: str) -> None:
    """Write the swing-weighted per-moment figures (columns 3 and 4 of ``sums``' rows) into a manifest."""
    from service.core.manifest import Evaluation, read_manifest, write_manifest

    metrics = {}
    for group, total in sums.items():
        metrics[f"real_window_joint_swing_accuracy/{group}"] = round(float(total[3] / total[0]), 5)
        metrics[f"real_window_joint_swing_accuracy_ignoring_side/{group}"] = round(float(total[4] / total[0]), 5)
        metrics[f"n_windows/{group}"] = float(total[0])
    manifest = read_manifest(model_dir / "manifest.json")
    evaluation = Evaluation(
        name=SWING_LOSO,
        command=command,
        data=f"real recordings, leave one person out: the folds of real-loso summary run {summary_run_id}; moving "
        "windows, one-to-one per moment weighing how the sensors swing together (service.core.assignment.SWING)",
        metrics=metrics,
    )
    manifest.evaluations = [e for e in manifest.evaluations if e.name != SWING_LOSO] + [evaluation]
    write_manifest(manifest, model_dir / "manifest.json")
