"""Joint sensor-to-segment assignment from per-window class probabilities, and motion detection.

Evidence of a sensor is the sum of log-probabilities over its windows; the one-to-one assignment
maximising the total is ``scipy.optimize.linear_sum_assignment`` (per-trial joint assignment is right more
often than single windows: docs/conventions.md, "Evaluation protocol"). ``window_joint_assignment`` applies the same
constraint to each moment on its own: the windows that sensors worn together recorded at the same time. Both can
weigh how the sensors swing together (``SWING``): the sensors of one leg swing together, the two legs take turns.
The per-moment answers can also weigh which side each leg sensor is on by how the pelvis sways (``sway_table``).

Both take what a user declares about where the sensors are: ``worn``, the segments the sensors are on (say both
feet, not saying which is which), and ``candidates``, per sensor the segments it may be on (say "a foot", not
saying which). The answers are then drawn from the declared segments only. That is the assignment conditioned on
the declaration: renormalising each window's probabilities over a sensor's allowed segments adds a per-sensor
constant to each of its candidates' evidence, which changes neither the one-to-one optimum nor the margins, so
forbidding the other cells is enough.
"""

from __future__ import annotations

import itertools
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from scipy.optimize import linear_sum_assignment

from service.core.manifest import ConfidenceSpec, SessionConfidenceSpec
from service.core.rotations import matrix_from_quat
from service.core.segments import BODY_PART, SEGMENTS

# A window whose gyroscope norm stays under this mean carries no gait information.
STILL_GYR_MEAN_RADS = 0.35


def gyro_norm(windows: np.ndarray) -> np.ndarray:
    """``(..., T, 6)`` windows → ``(..., T)``: the norm of each sample's angular velocity, which does not depend on
    how the sensor is mounted (what ``is_moving`` and the swing of sensors worn together read)."""
    return np.linalg.norm(windows[..., 3:6], axis=-1)


def is_moving(windows: np.ndarray) -> np.ndarray:
    """``(N, T, 6)`` → ``(N,)`` bool: mean gyroscope norm above ``STILL_GYR_MEAN_RADS``."""
    return gyro_norm(windows).mean(axis=-1) > STILL_GYR_MEAN_RADS


def turns_about_vertical(windows: np.ndarray, within_deg: float = 45.0) -> np.ndarray:
    """Per window ``(B, T, 6)``: is the dominant rotation axis (top eigenvector of Σ ω ωᵀ) within ``within_deg`` of
    the mean specific force, i.e. does the segment mostly twist or turn about the vertical rather than swing?

    A label-free description of what a window contains: in gait the legs and feet swing about their flexion axis,
    which is horizontal, and the training clips are gait, so a leg or foot window that turns about the vertical is
    outside what the models know. The service returns it per window; ``training.i2s.evaluate.evaluate_real`` reports
    the share per recording. (The pelvis turns about the vertical in gait too.)
    """
    if not len(windows):
        return np.zeros(0, dtype=bool)
    up = windows[..., :3].mean(axis=1).astype(np.float64)
    up /= np.maximum(np.linalg.norm(up, axis=1, keepdims=True), 1e-9)  # no specific force (free fall): False
    gyr = windows[..., 3:].astype(np.float64)
    axis = np.linalg.eigh(np.einsum("bti,btj->bij", gyr, gyr))[1][..., -1]
    return np.abs(np.einsum("bi,bi->b", axis, up)) > np.cos(np.radians(within_deg))


@dataclass(frozen=True)
class JointAssignment:
    segment: np.ndarray  # (S,) class index per sensor, -1 if unassigned (more sensors than segments)
    evidence: np.ndarray  # (S, K) summed log-probabilities
    confidence: np.ndarray  # (S,) softmax of the evidence at the chosen class
    # (S,) evidence of the assigned class minus the best other class (< 0: constraint overrode it); with the swing
    # weighed, what the whole answer wins by over the best that moves the sensor (``joint_assignment``)
    margin: np.ndarray


def worn_classes(worn: Sequence[int] | None, n_classes: int) -> np.ndarray:
    """The declared segments as sorted class indices (all ``n_classes`` when ``worn`` is None)."""
    if worn is None:
        return np.arange(n_classes)
    classes = np.asarray(sorted(worn), dtype=np.int64)
    if not len(classes) or len(set(classes.tolist())) != len(classes) or classes[0] < 0 or classes[-1] >= n_classes:
        raise ValueError(f"worn must be distinct class indices in [0, {n_classes}), at least one; got {list(worn)}")
    return classes


Candidates = Sequence[Sequence[int] | None]


def allowed_segments(
    n_sensors: int, n_classes: int, worn: Sequence[int] | None = None, candidates: Candidates | None = None
) -> np.ndarray:
    """``(n_sensors, n_classes)`` bool: the segments each sensor may be on, ``worn`` ∩ its ``candidates[s]``
    (None: no restriction). Every sensor keeps at least one segment, or ``ValueError``."""
    allowed = np.zeros((n_sensors, n_classes), dtype=bool)
    allowed[:, worn_classes(worn, n_classes)] = True
    if candidates is None:
        return allowed
    if len(candidates) != n_sensors:
        raise ValueError(f"candidates must have one entry per sensor ({n_sensors}), got {len(candidates)}")
    for s, own in enumerate(candidates):
        if own is not None:
            allowed[s] &= np.isin(np.arange(n_classes), worn_classes(own, n_classes))
    if not allowed.any(axis=1).all():
        empty = np.flatnonzero(~allowed.any(axis=1)).tolist()
        raise ValueError(f"sensors {empty}: none of their candidate segments is among the worn ones {worn}")
    return allowed


def _best(evidence: np.ndarray, allowed: np.ndarray, allow_shared: bool) -> np.ndarray:
    """Per row of ``evidence`` ``(S, K)``, its class among the row's ``allowed`` ones: the one-to-one optimum of the
    summed evidence (-1 for rows left over: more rows than classes, or rows whose allowed classes others took), or
    each row's own best."""
    among = np.where(allowed, evidence, -np.inf)
    if allow_shared or len(evidence) == 1:  # one row: the one-to-one optimum is its own best class
        return among.argmax(axis=1)
    # A forbidden cell costs more than any matching of allowed cells can differ by, so the optimum fills as many
    # rows as the declaration allows and is the best of those; rows that still land on a forbidden cell get -1.
    finite = evidence[allowed]
    floor = finite.min() - 2.0 * np.abs(finite).sum() - 1.0
    rows, cols = linear_sum_assignment(np.where(allowed, evidence, floor), maximize=True)
    segment = np.full(len(evidence), -1, dtype=np.int64)
    keep = allowed[rows, cols]
    segment[rows[keep]] = cols[keep]
    return segment


# How two sensors' windows of one moment swing together: the Pearson correlation of their gyroscope norms over the
# window, as Fisher z = atanh(r). The thigh, shank and foot of one leg swing together, the two legs take turns, and
# the pelvis follows neither, so z tells the pairs apart by where both sensors are (``swing_pair_type``): per type
# the mean and standard deviation of z on the moving windows of the simulated walking clips of
# ``i2s_assignment.yaml``'s training subjects (``training.i2s.swing.fit_swing``, which
# tests/training/i2s/test_swing.py checks these against). Our addition to Zimmermann et al. 2018.
SWING_PAIR_TYPES: tuple[str, ...] = (
    "pelvis-foot",
    "pelvis-lower_leg",
    "pelvis-upper_leg",
    "same_leg-foot-lower_leg",
    "same_leg-foot-upper_leg",
    "same_leg-lower_leg-upper_leg",
    "both_legs-foot-foot",
    "both_legs-foot-lower_leg",
    "both_legs-foot-upper_leg",
    "both_legs-lower_leg-lower_leg",
    "both_legs-lower_leg-upper_leg",
    "both_legs-upper_leg-upper_leg",
)
SWING: dict[str, tuple[float, float]] = {  # pair type: mean and standard deviation of z (318–636 windows each)
    "pelvis-foot": (0.186, 0.144),
    "pelvis-lower_leg": (0.073, 0.175),
    "pelvis-upper_leg": (0.110, 0.208),
    "same_leg-foot-lower_leg": (0.869, 0.205),
    "same_leg-foot-upper_leg": (0.313, 0.171),
    "same_leg-lower_leg-upper_leg": (0.011, 0.251),
    "both_legs-foot-foot": (-0.688, 0.157),
    "both_legs-foot-lower_leg": (-0.506, 0.135),
    "both_legs-foot-upper_leg": (-0.378, 0.148),
    "both_legs-lower_leg-lower_leg": (-0.528, 0.174),
    "both_legs-lower_leg-upper_leg": (-0.048, 0.153),
    "both_legs-upper_leg-upper_leg": (-0.060, 0.207),
}
# The weight of the swing evidence per pair against the windows' own log-probabilities: the pairs of one moment are
# not independent (a leg's three sensors make three pairs out of one stride), so their log-likelihoods are tempered.
# Chosen among 1, 1/2, 1/4, 1/8, 1/16, 1/32 and 1/(S - 1) by the per-moment accuracy on the validation people of the
# real recordings (docs/models.md, "Sensors that swing together").
SWING_WEIGHT = 0.125
_Z_CLIP = 3.0  # |r| ≤ 0.995


def swing_pair_type(a: int, b: int) -> int:
    """The ``SWING_PAIR_TYPES`` index of a sensor on class ``a`` worn with one on class ``b`` (a ≠ b)."""
    parts = sorted((BODY_PART[a], BODY_PART[b]), key=("pelvis", "foot", "lower_leg", "upper_leg").index)
    if parts[0] == "pelvis":
        return SWING_PAIR_TYPES.index(f"pelvis-{parts[1]}")
    relation = "same_leg" if (a < 3) == (b < 3) else "both_legs"
    return SWING_PAIR_TYPES.index(f"{relation}-{parts[0]}-{parts[1]}")


def swing_z(gyro_norms: np.ndarray) -> np.ndarray:
    """``(..., S, T)`` gyroscope norms of S sensors' windows of one moment → ``(..., S, S)`` Fisher z of their
    Pearson correlations, clipped to ±``_Z_CLIP`` (0 on the diagonal and for a window whose norm does not vary)."""
    x = np.asarray(gyro_norms, dtype=np.float64)
    x = x - x.mean(axis=-1, keepdims=True)
    scale = np.linalg.norm(x, axis=-1)
    with np.errstate(invalid="ignore", divide="ignore"):
        r = (x @ np.swapaxes(x, -1, -2)) / (scale[..., :, None] * scale[..., None, :])
    return _fisher_z(np.where(np.eye(x.shape[-2], dtype=bool), 0.0, r))


def _fisher_z(r: np.ndarray) -> np.ndarray:
    """Pearson correlations → their Fisher z, clipped to ±``_Z_CLIP`` (0 where a correlation is not finite: a window
    that does not vary)."""
    r = np.nan_to_num(r, nan=0.0, posinf=0.0, neginf=0.0)
    return np.clip(np.arctanh(np.clip(r, -0.999999, 0.999999)), -_Z_CLIP, _Z_CLIP)


def _normal_log_density(z: np.ndarray, mean: np.ndarray, std: np.ndarray) -> np.ndarray:
    return -0.5 * ((z - mean) / std) ** 2 - np.log(std) - 0.5 * np.log(2 * np.pi)


def _pair_type_table() -> np.ndarray:
    table = np.zeros((len(SEGMENTS), len(SEGMENTS)), dtype=np.int64)
    for a in range(len(SEGMENTS)):
        for b in range(len(SEGMENTS)):
            if a != b:
                table[a, b] = swing_pair_type(a, b)
    return table


_PAIR_TYPE = _pair_type_table()


def swing_log_likelihood(gyro_norms: np.ndarray) -> np.ndarray:
    """``(..., S, T)`` → ``(..., S, S, len(SWING_PAIR_TYPES))``: per pair of sensors, the log-density of their
    ``swing_z`` under each pair type's normal distribution (``SWING``)."""
    z = swing_z(gyro_norms)
    mean, std = (np.array([SWING[name][k] for name in SWING_PAIR_TYPES]) for k in (0, 1))
    return _normal_log_density(z[..., None], mean, std)


def swing_per_moment(gyro_norms: list[np.ndarray], moving: list[np.ndarray]) -> np.ndarray:
    """Per sensor its windows' gyroscope norms ``(N_s, T)`` and moving mask ``(N_s,)`` → ``(n, S, S, types)``
    float32: per moment (window index, the first n = min N_s) the ``swing_log_likelihood`` of every pair of sensors
    whose windows both move there, 0 for the others and on the diagonal. Summed over a session's moments it is the
    session's evidence of how its sensors swing together (``joint_assignment``'s ``swing``)."""
    n_sensors = len(gyro_norms)
    n = min((len(g) for g in gyro_norms), default=0)
    out = np.zeros((n, n_sensors, n_sensors, len(SWING_PAIR_TYPES)), dtype=np.float32)
    if n_sensors < 2 or n == 0:
        return out
    both = np.stack([m[:n] for m in moving], axis=1)  # (n, S)
    both = both[:, :, None] & both[:, None, :] & ~np.eye(n_sensors, dtype=bool)
    for lo in range(0, n, 512):  # (512, S, S, types) float64 at a time
        hi = min(lo + 512, n)
        chunk = swing_log_likelihood(np.stack([g[lo:hi] for g in gyro_norms], axis=1))
        out[lo:hi] = np.where(both[lo:hi, :, :, None], chunk, 0.0)
    return out


# Which side a leg sensor is on, read off how the pelvis sways (our addition; weighed by the evaluation of
# ``training.i2s.swing``, not yet by the service's answers: docs/models.md, "The pelvis' sway"). In walking the body
# leans over the leg it stands on, so the pelvis' sideways specific force (along its y, left, with the gravity its
# roll tilts in) follows which leg swings: the Fisher z of its correlation with a leg sensor's gyroscope norm over a
# window is positive for a left leg sensor and negative for a right one on real people. Per leg class a normal of
# that z (``sway_table``), fitted on real people (``training.i2s.swing.fit_sway``).
_PELVIS = SEGMENTS.index("Pelvis")


def sway_table(table: dict[str, tuple[float, float]]) -> tuple[np.ndarray, np.ndarray]:
    """Per leg class name (mean, standard deviation) of ``sway_z`` → per-class arrays ``(K,)``, ``(K,)`` (the
    pelvis and any class not named: 0, 1)."""
    mean = np.array([table.get(name, (0.0, 1.0))[0] for name in SEGMENTS])
    std = np.array([table.get(name, (0.0, 1.0))[1] for name in SEGMENTS])
    return mean, std


def pelvis_lateral(windows: np.ndarray, q_pelvis: np.ndarray) -> np.ndarray:
    """``(N, T, 6)`` windows of one sensor and the ``(4,)`` q_segment_imu of its pelvis hypothesis (w first) →
    ``(N, T)``: the specific force along the pelvis' y (left) were the sensor on the pelvis."""
    return windows[..., :3] @ matrix_from_quat(np.asarray(q_pelvis, dtype=np.float64))[1]


def sway_z(lateral: np.ndarray, gyro_norms: np.ndarray) -> np.ndarray:
    """The pelvis sensor's window ``(..., T)`` (``pelvis_lateral``) and the sensors' gyroscope norms ``(..., S, T)``
    over the same moment → ``(..., S)``: the Fisher z of their correlations, clipped to ±``_Z_CLIP``."""
    a = lateral - lateral.mean(axis=-1, keepdims=True)
    b = gyro_norms - gyro_norms.mean(axis=-1, keepdims=True)
    with np.errstate(invalid="ignore", divide="ignore"):
        r = (b @ a[..., :, None])[..., 0] / (np.linalg.norm(b, axis=-1) * np.linalg.norm(a, axis=-1)[..., None])
    return _fisher_z(r)


def sway_log_likelihood(z: np.ndarray, table: tuple[np.ndarray, np.ndarray]) -> np.ndarray:
    """``(...,)`` ``sway_z`` → ``(..., K)``: its log-density under each leg class's normal (``sway_table``), 0 for the
    pelvis class."""
    mean, std = table
    ll = _normal_log_density(np.asarray(z)[..., None], mean, std)
    ll[..., _PELVIS] = 0.0
    return ll


def _with_sway(
    first: np.ndarray,
    evidence: np.ndarray,
    allowed: np.ndarray,
    pair_ll: np.ndarray,
    swing_weight: float,
    laterals: np.ndarray,
    norms: np.ndarray,
    weight: float,
    table: tuple[np.ndarray, np.ndarray],
) -> np.ndarray:
    """``_best_with_swing_moments``' answers ``first`` ``(M, S)`` answered again where they put a sensor on the
    pelvis: every other sensor's evidence gains ``weight`` × the log-likelihood of how that sensor's swing follows
    the pelvis' sway (``laterals`` ``(M, S, T)``, each sensor's ``pelvis_lateral``, NaN where the sensor's pelvis
    frame is not known yet: that moment is left as it was; ``norms`` ``(M, S, T)``)."""
    has = first == _PELVIS
    moments = np.flatnonzero(has.any(axis=1))
    pelvis = has[moments].argmax(axis=1)
    settled = np.isfinite(laterals[moments, pelvis]).all(axis=-1)  # the pelvis sensor's frame is known there
    moments, pelvis = moments[settled], pelvis[settled]
    if not len(moments):
        return first
    ll = sway_log_likelihood(sway_z(laterals[moments, pelvis], norms[moments]), table)  # (M', S, K)
    ll[np.arange(len(moments)), pelvis] = 0.0
    out = first.copy()
    out[moments] = _best_with_swing_moments(evidence[moments] + weight * ll, allowed, pair_ll[moments], swing_weight)
    return out


_FORBIDDEN = -1e9  # a forbidden cell's score in ``_swing_search`` (finite: it is summed by a matrix product)
_MAPS: dict[int, tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]] = {}


def _maps_of(n_rows: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Every one-to-one map of ``n_rows`` rows into the seven classes ``(P, n_rows)`` (P = 5,040 for seven rows),
    the row pairs ``i < j``, and per map the one-hot selection ``(P, n_rows · 7 + pairs · types)`` of its cells
    (row, class) and of its pairs' ``SWING_PAIR_TYPES``: a map's score is this times the scores of all cells and
    pair types, one matrix product for all maps."""
    if n_rows not in _MAPS:
        n_classes, n_types = len(SEGMENTS), len(SWING_PAIR_TYPES)
        maps = np.array(list(itertools.permutations(range(n_classes), n_rows)), dtype=np.int64)
        rows_i, rows_j = np.triu_indices(n_rows, 1)
        cells = np.arange(n_rows) * n_classes + maps
        pairs = n_rows * n_classes + np.arange(len(rows_i)) * n_types + _PAIR_TYPE[maps[:, rows_i], maps[:, rows_j]]
        select = np.zeros((len(maps), n_rows * n_classes + len(rows_i) * n_types), dtype=np.float32)
        np.put_along_axis(select, np.concatenate([cells, pairs], axis=1), 1.0, axis=1)
        _MAPS[n_rows] = (maps, rows_i, rows_j, select)
    return _MAPS[n_rows]


def _swing_search(
    evidence: np.ndarray, allowed: np.ndarray, pair_ll: np.ndarray, weight: float
) -> tuple[np.ndarray, np.ndarray] | None:
    """The one-to-one answer of the rows of ``evidence`` ``(S, K)`` that maximises their summed log-probabilities
    plus, per pair of rows, ``weight`` × the log-likelihood of how they swing together given where the answer puts
    them (``pair_ll`` ``(S, S, types)``, ``swing_log_likelihood`` or its sum over moments): the sensors of one leg
    are answered together, so a thigh whose own windows lean to the wrong side follows its shank and foot. Exact,
    over every one-to-one map (5,040 for seven sensors); and per row how much the best map that puts the row
    elsewhere scores less (+inf where no allowed map does). None with more rows than classes, or no map that keeps
    every row on an allowed class (the caller then answers with ``_best``)."""
    n_rows, n_classes = evidence.shape
    if n_rows > n_classes or n_classes != len(SEGMENTS):
        return None
    maps, rows_i, rows_j, select = _maps_of(n_rows)
    scores = np.concatenate([np.where(allowed, evidence, _FORBIDDEN).ravel(), weight * pair_ll[rows_i, rows_j].ravel()])
    totals = select @ scores.astype(np.float32)
    best = int(np.argmax(totals))
    if not allowed[np.arange(n_rows), maps[best]].all():  # no map keeps every row on an allowed class
        return None
    feasible = totals > _FORBIDDEN / 2
    gap = np.full(n_rows, np.inf)
    for row in range(n_rows):
        elsewhere = feasible & (maps[:, row] != maps[best, row])
        if elsewhere.any():
            gap[row] = float(totals[best]) - float(totals[elsewhere].max())
    return maps[best], gap


def joint_assignment(
    log_probs: list[np.ndarray],
    allow_shared: bool = False,
    worn: Sequence[int] | None = None,
    candidates: Candidates | None = None,
    swing: np.ndarray | None = None,
    swing_weight: float = SWING_WEIGHT,
) -> JointAssignment:
    """Assign S sensors (each ``(N_s, K)`` window log-probabilities) to K segments, or to the declared ones.

    One-to-one by default: with more sensors than segments the weakest are left unassigned (-1);
    with fewer, segments stay empty. ``allow_shared`` lets sensors share a segment (per-sensor argmax).
    With ``worn`` / ``candidates`` (``allowed_segments``), a sensor's evidence for the segments it may not be on is
    -inf, and its confidence and margin are over those it may be on (margin +inf when it may be on one only).
    With ``swing`` ``(S, S, types)``, the session's summed ``swing_per_moment``, the one-to-one answer also weighs
    how the sensors swung together (``_swing_search``, by ``swing_weight``; 0: not weighed); the margin is then
    how much more the answer scores, the swing included, than the best one-to-one answer that puts the sensor on
    another segment (≥ 0; +inf where none may), and the confidence stays that of the sensor's own evidence.
    """
    evidence = np.stack([lp.sum(axis=0) for lp in log_probs])
    n_sensors, n_classes = evidence.shape
    allowed = allowed_segments(n_sensors, n_classes, worn, candidates)
    evidence[~allowed] = -np.inf
    found = None
    if swing is not None and swing_weight > 0 and not allow_shared and n_sensors > 1:
        found = _swing_search(evidence, allowed, swing, swing_weight)
    segment = _best(evidence, allowed, allow_shared) if found is None else found[0]
    rows, chosen = np.arange(n_sensors), np.maximum(segment, 0)
    post = np.exp(evidence - evidence.max(axis=1, keepdims=True))
    post /= post.sum(axis=1, keepdims=True)
    confidence = np.where(segment >= 0, post[rows, chosen], 0.0)
    others = evidence.copy()
    others[rows, chosen] = -np.inf
    with np.errstate(invalid="ignore"):  # -inf - -inf never reaches the answer: those rows have one segment
        margin = np.where(allowed.sum(axis=1) > 1, evidence[rows, chosen] - others.max(axis=1), np.inf)
    if found is not None:  # the score the answer wins by, the swing included, over any that moves the sensor
        margin = found[1]
    margin = np.where(segment >= 0, margin, 0.0)
    return JointAssignment(segment, evidence, confidence, margin)


def session_assignment(
    log_probs: list[np.ndarray],
    moving: list[np.ndarray],
    allow_shared: bool = False,
    worn: Sequence[int] | None = None,
    candidates: Candidates | None = None,
    gyro_norms: list[np.ndarray] | None = None,
    swing: np.ndarray | None = None,
    swing_weight: float = SWING_WEIGHT,
) -> tuple[JointAssignment, np.ndarray, np.ndarray]:
    """The joint answer of sensors worn together, as ``/v1/imu/assign`` gives it: each sensor's evidence is its
    moving windows (all its windows if none moves; ``log_probs[s]`` ``(N_s, K)``, ``moving[s]`` ``(N_s,)``), and
    with ``gyro_norms`` (per sensor ``(N_s, T)``) how the sensors swung together at the moments they all recorded
    (``swing_per_moment``; or ``swing``, their sum, where the caller has it).
    Returns the assignment, per sensor the votes of its moving windows (``vote_counts``) and their number: what
    ``confidence_features`` reads."""
    evidence = [lp[m] if m.any() else lp for lp, m in zip(log_probs, moving, strict=True)]
    if swing is None and gyro_norms is not None and swing_weight > 0:
        swing = swing_per_moment(gyro_norms, moving).sum(axis=0, dtype=np.float64)
    joint = joint_assignment(evidence, allow_shared, worn, candidates, swing, swing_weight)
    n_classes = log_probs[0].shape[1]
    votes = np.stack([vote_counts(lp[m], n_classes) for lp, m in zip(log_probs, moving, strict=True)])
    return joint, votes, np.array([int(m.sum()) for m in moving])


def window_joint_assignment(
    log_probs: list[np.ndarray],
    moving: list[np.ndarray],
    allow_shared: bool = False,
    worn: Sequence[int] | None = None,
    candidates: Candidates | None = None,
    gyro_norms: list[np.ndarray] | None = None,
    swing_weight: float = SWING_WEIGHT,
    laterals: list[np.ndarray] | None = None,
    sway: tuple[np.ndarray, np.ndarray] | None = None,
    sway_weight: float = 0.0,
) -> list[np.ndarray]:
    """One-to-one assignment per moment: window ``t`` of every sensor is assigned from those windows alone.

    ``log_probs[s]`` is ``(N_s, K)`` for sensor ``s`` and ``moving[s]`` its ``(N_s,)`` mask (``is_moving``);
    windows with the same index are taken as recorded at the same time. At each index the sensors whose window
    there moves share out the K segments (or the declared ones, ``allowed_segments``) one-to-one (the answer that
    maximises their summed log-probability); a still window, or one left over when more windows move than there
    are segments for them, gets -1. Zimmermann et al. 2018 classifies every window on its own (§2.2) and names the
    left/right switches that this leaves as future work (§5); the sensors of one body cannot sit on the same segment, so
    at one moment their windows constrain each other. ``allow_shared`` (as in ``joint_assignment``) gives each moving
    window its own best allowed class instead.

    With ``gyro_norms`` (per sensor ``(N_s, T)``, each window's gyroscope norm) the answer also weighs how the
    sensors swing together (``_swing_search``, by ``swing_weight``): the thigh, shank and foot of one leg do, the
    two legs take turns. Our addition to the paper's per-window answer; each moment is still answered from its own
    windows. With ``laterals`` too (per sensor ``(N_s, T)``, its windows' ``pelvis_lateral``) and a ``sway`` table
    (``sway_table``), a moment whose answer puts a sensor on the pelvis is answered again with the side evidence of
    how the others follow its sway, by ``sway_weight``.

    Returns one ``(N_s,)`` int array per sensor.
    """
    n_classes = log_probs[0].shape[1] if log_probs else 0
    allowed = allowed_segments(len(log_probs), n_classes, worn, candidates)
    if allow_shared:
        return [
            np.where(m, np.where(a, lp, -np.inf).argmax(axis=1), -1)
            for lp, m, a in zip(log_probs, moving, allowed, strict=True)
        ]
    out = [np.full(len(lp), -1, dtype=np.int64) for lp in log_probs]
    moments: dict[tuple[int, ...], list[int]] = {}  # the sensors whose windows move → the moments they do
    for t in range(max((len(lp) for lp in log_probs), default=0)):
        present = tuple(s for s, lp in enumerate(log_probs) if t < len(lp) and moving[s][t])
        if present:
            moments.setdefault(present, []).append(t)
    for present, times in moments.items():
        rows = list(present)
        if gyro_norms is not None and 1 < len(rows) <= len(SEGMENTS) == n_classes:
            for lo in range(0, len(times), _MOMENTS_PER_CALL):
                chunk = times[lo : lo + _MOMENTS_PER_CALL]
                evidence = np.stack([[log_probs[s][t] for s in rows] for t in chunk])
                norms = np.stack([[gyro_norms[s][t] for s in rows] for t in chunk])
                pair_ll = swing_log_likelihood(norms)
                answers = _best_with_swing_moments(evidence, allowed[rows], pair_ll, swing_weight)
                if laterals is not None and sway is not None and sway_weight > 0:
                    lateral = np.stack([[laterals[s][t] for s in rows] for t in chunk])
                    answers = _with_sway(
                        answers, evidence, allowed[rows], pair_ll, swing_weight, lateral, norms, sway_weight, sway
                    )
                for t, answer in zip(chunk, answers, strict=True):
                    for s, c in zip(rows, answer.tolist(), strict=True):
                        out[s][t] = c
            continue
        for t in times:
            answer = _best(np.stack([log_probs[s][t] for s in rows]), allowed[rows], allow_shared=False)
            for s, c in zip(rows, answer.tolist(), strict=True):
                out[s][t] = c
    return out


_MOMENTS_PER_CALL = 256  # (256, 5,040) float32 scores at a time


def _best_with_swing_moments(
    evidence: np.ndarray, allowed: np.ndarray, pair_ll: np.ndarray, weight: float
) -> np.ndarray:
    """``_swing_search``'s answers for M moments of the same rows at once: ``evidence`` ``(M, S, K)``, ``pair_ll``
    ``(M, S, S, types)`` → ``(M, S)``; one matrix product for all of them."""
    n_moments, n_rows, _ = evidence.shape
    maps, rows_i, rows_j, select = _maps_of(n_rows)
    scores = np.concatenate(
        [
            np.where(allowed, evidence, _FORBIDDEN).reshape(n_moments, -1),
            weight * pair_ll[:, rows_i, rows_j].reshape(n_moments, -1),
        ],
        axis=1,
    )
    best = maps[np.argmax(scores.astype(np.float32) @ select.T, axis=1)]
    for m in np.flatnonzero(~allowed[np.arange(n_rows), best].all(axis=1)):  # no map keeps every row allowed
        best[m] = _best(evidence[m], allowed, allow_shared=False)
    return best


class MomentAssembler:
    """``window_joint_assignment`` for a live session, whose sensors' windows arrive one packet at a time.

    A moment is a window end time (seconds on the sensors' shared clock, rounded to the microsecond). Its windows
    wait until every sensor of the session has produced a window at or after that time, then the moment is
    answered from the windows it holds; a sensor that stalls, or never sends, holds up at most ``max_open``
    moments, after which the oldest are answered without it. ``flush`` answers all that wait (end of stream).
    With ``allow_shared`` each moving window keeps its own answer; with ``worn`` / ``candidates`` the answers are
    drawn from the declared segments only (``allowed_segments``). ``swing`` sums how the sensors swung together
    over the moments answered so far (``swing_per_moment``), for the session's joint answer.
    """

    def __init__(
        self,
        n_sensors: int,
        allow_shared: bool = False,
        max_open: int = 32,
        worn: Sequence[int] | None = None,
        candidates: Candidates | None = None,
    ) -> None:
        self.allow_shared = allow_shared
        allowed_segments(n_sensors, len(SEGMENTS), worn, candidates)  # a bad declaration fails here, not mid-stream
        self.worn = None if worn is None else tuple(worn)
        self.candidates = [None] * n_sensors if candidates is None else list(candidates)
        self.max_open = max_open
        self.latest = np.full(n_sensors, -np.inf)  # newest window end per sensor
        # the answered moments' ``swing_per_moment``, summed: how the sensors swung together so far
        self.swing = np.zeros((n_sensors, n_sensors, len(SWING_PAIR_TYPES)))
        self.open: dict[float, dict[int, tuple[np.ndarray, bool, np.ndarray | None]]] = {}

    def add(
        self, sensor: int, end_s: float, log_probs: np.ndarray, moving: bool, gyro_norm: np.ndarray | None = None
    ) -> None:
        """One window of ``sensor``: its ``(K,)`` log-probabilities, whether it moves (``is_moving``) and its
        gyroscope norm ``(T,)``, for how the sensors swing together (``window_joint_assignment``; a moment with a
        window that has none is answered without)."""
        key = round(end_s, 6)
        self.open.setdefault(key, {})[sensor] = (log_probs, moving, gyro_norm)
        self.latest[sensor] = max(self.latest[sensor], key)

    def ready(self) -> list[tuple[float, dict[int, int]]]:
        """The moments every sensor has reached (and the oldest beyond ``max_open``), oldest first:
        (end time, sensor → class index, -1 for a still or left-over window)."""
        horizon = self.latest.min()
        keys = sorted(self.open)
        n_done = sum(k <= horizon for k in keys)
        n_done = max(n_done, len(keys) - self.max_open)
        return [self._answer(k) for k in keys[:n_done]]

    def flush(self) -> list[tuple[float, dict[int, int]]]:
        return [self._answer(k) for k in sorted(self.open)]

    def _answer(self, key: float) -> tuple[float, dict[int, int]]:
        windows = self.open.pop(key)
        sensors = list(windows)
        log_probs = [windows[s][0][None] for s in sensors]
        moving = [np.array([windows[s][1]]) for s in sensors]
        norms = None if any(windows[s][2] is None for s in sensors) else [windows[s][2][None] for s in sensors]
        swinging = [s for s in sensors if windows[s][1]]
        if norms is not None and len(swinging) > 1:
            pair_ll = swing_log_likelihood(np.stack([windows[s][2] for s in swinging]))
            pair_ll[np.arange(len(swinging)), np.arange(len(swinging))] = 0.0
            self.swing[np.ix_(swinging, swinging)] += pair_ll
        candidates = [self.candidates[s] for s in sensors]
        answer = window_joint_assignment(log_probs, moving, self.allow_shared, self.worn, candidates, norms)
        return key, {s: int(a[0]) for s, a in zip(sensors, answer, strict=True)}


# What the calibrated confidence of a joint assignment reads, per sensor (``confidence_features``).
CONFIDENCE_FEATURES = ("vote_share", "margin_per_window", "log_moving_windows")
# The session's: the logit of the product of its sensors' probabilities (what every sensor being right would have if
# the sensors erred independently; they do not: a swap makes two wrong at once) and log(number of sensors).
SESSION_FEATURES = ("logit_product_p_correct", "log_sensors")
_MARGIN_CLIP = 10.0  # per window; a sensor the declarations leave one segment (margin +inf) reads as this
_LOGIT_CLIP = 30.0


@dataclass(frozen=True)
class SessionConfidence:
    """The probability that a session's whole joint assignment is right: a logistic function of
    ``session_features``, and the probability the service commits at."""

    coef: tuple[float, ...]
    intercept: float
    threshold: float

    def p(self, features: np.ndarray) -> np.ndarray:
        """``(N, len(SESSION_FEATURES))`` → ``(N,)`` probabilities."""
        return _logistic(features @ np.asarray(self.coef) + self.intercept)


@dataclass(frozen=True)
class ConfidenceModel:
    """The probability that a sensor's joint assignment is right: a logistic function of ``confidence_features``,
    fitted on sessions of people the model never trained on (``training.i2s.calibration``), and when to commit.

    Without ``session`` the service commits to a session's answer when every assigned sensor reaches ``threshold``;
    with it, when the probability that every assigned sensor is right (``p_all_correct``) reaches
    ``session.threshold``. Either way each sensor needs ``min_moving_windows`` moving windows; otherwise the status is
    ``not_enough_walking``."""

    coef: tuple[float, ...]
    intercept: float
    threshold: float
    min_moving_windows: int
    session: SessionConfidence | None = None
    swing_weight: float = 0.0  # of how the sensors swing together, in the answers it was fitted on

    @classmethod
    def from_spec(cls, spec: ConfidenceSpec | None) -> ConfidenceModel | None:
        """From a manifest's ``confidence`` section (``service.core.manifest.ConfidenceSpec``), None without one;
        ``ValueError`` if its features are not ``CONFIDENCE_FEATURES`` (``SESSION_FEATURES`` for ``session``)."""
        if spec is None:
            return None
        if tuple(spec.features) != CONFIDENCE_FEATURES or len(spec.coef) != len(CONFIDENCE_FEATURES):
            raise ValueError(f"confidence features must be {CONFIDENCE_FEATURES}, got {spec.features}")
        session = None
        if spec.session is not None:
            if tuple(spec.session.features) != SESSION_FEATURES or len(spec.session.coef) != len(SESSION_FEATURES):
                raise ValueError(f"session confidence features must be {SESSION_FEATURES}, got {spec.session.features}")
            session = SessionConfidence(tuple(spec.session.coef), spec.session.intercept, spec.session.threshold)
        return cls(
            tuple(spec.coef), spec.intercept, spec.threshold, spec.min_moving_windows, session, spec.swing_weight
        )

    def session_spec(self) -> SessionConfidenceSpec | None:
        if self.session is None:
            return None
        return SessionConfidenceSpec(
            features=list(SESSION_FEATURES),
            coef=list(self.session.coef),
            intercept=self.session.intercept,
            threshold=self.session.threshold,
        )

    def p_correct(self, features: np.ndarray) -> np.ndarray:
        """``(S, len(CONFIDENCE_FEATURES))`` → ``(S,)`` probabilities."""
        return _logistic(features @ np.asarray(self.coef) + self.intercept)

    def p_all_correct(self, p_correct: np.ndarray, assigned: np.ndarray) -> float | None:
        """The probability that every assigned sensor is right (``session``); None without a session calibration
        or with no assigned sensor."""
        if self.session is None or not assigned.any():
            return None
        return float(self.session.p(session_features(p_correct[assigned])[None])[0])

    def committed(self, p_correct: np.ndarray, moving_windows: np.ndarray, assigned: np.ndarray) -> np.ndarray:
        """Per sensor: it has a segment, ``min_moving_windows`` moving windows and ``p_correct`` at the threshold.
        These are the answers whose share of right ones is the calibration's selective accuracy; a session whose
        weakest sensor stays below (the thighs of a seven-sensor suit, often) still commits the others."""
        return assigned & (moving_windows >= self.min_moving_windows) & (p_correct >= self.threshold)

    def status(self, p_correct: np.ndarray, moving_windows: np.ndarray, assigned: np.ndarray) -> str:
        """``assigned`` when every sensor that got a segment has ``min_moving_windows`` moving windows and the
        probability that decides (the class docstring) reaches its threshold; ``not_enough_walking`` otherwise (and
        with no assigned sensor)."""
        if not assigned.any() or not (moving_windows[assigned] >= self.min_moving_windows).all():
            return "not_enough_walking"
        if self.session is not None:
            sure = self.p_all_correct(p_correct, assigned) >= self.session.threshold  # type: ignore[operator]
        else:
            sure = bool(self.committed(p_correct, moving_windows, assigned)[assigned].all())
        return "assigned" if sure else "not_enough_walking"


def session_swing_weight(model: ConfidenceModel | None) -> float:
    """The weight of how the sensors swing together in a session's joint answer: the one the model's calibration was
    fitted with (a version calibrated before it was weighed keeps answering as it did), ``SWING_WEIGHT`` for a
    model without calibration."""
    return SWING_WEIGHT if model is None else model.swing_weight


def _logistic(z: np.ndarray) -> np.ndarray:
    return 1.0 / (1.0 + np.exp(-np.clip(z, -50.0, 50.0)))


def session_features(p_correct: np.ndarray) -> np.ndarray:
    """The assigned sensors' probabilities ``(S,)`` → ``SESSION_FEATURES`` ``(2,)``: logit of their product (clipped
    to ±30) and log S. With coefficients (1, 0) and intercept 0 the session's probability is that product."""
    log_all = float(np.log(np.clip(p_correct, 1e-12, 1.0)).sum())
    log_not_all = np.log(-np.expm1(log_all)) if log_all < 0.0 else -np.inf
    logit = float(np.clip(log_all - log_not_all, -_LOGIT_CLIP, _LOGIT_CLIP))
    return np.array([logit, np.log(len(p_correct))])


def confidence_features(segment: np.ndarray, margin: np.ndarray, votes: np.ndarray, moving: np.ndarray) -> np.ndarray:
    """Per sensor of a ``JointAssignment``: the share of its moving windows whose own most likely segment is the
    assigned one (``votes`` ``(S, K)``: per class, the moving windows that rank it first), the margin per moving
    window (clipped to ±10), and log(1 + moving windows). A sensor with no segment or no moving window reads 0 in
    the first two. The votes count each window's own best of all seven segments, also when a declaration
    (``worn`` / ``candidates``) allows fewer: the share is then lower, and the probability conservative."""
    n = np.maximum(moving, 1).astype(np.float64)
    rows = np.arange(len(segment))
    share = np.where((segment >= 0) & (moving > 0), votes[rows, np.maximum(segment, 0)] / n, 0.0)
    per_window = np.clip(
        np.nan_to_num(margin / n, posinf=_MARGIN_CLIP, neginf=-_MARGIN_CLIP), -_MARGIN_CLIP, _MARGIN_CLIP
    )
    return np.stack([share, np.where(moving > 0, per_window, 0.0), np.log1p(moving)], axis=1)


def vote_counts(log_probs: np.ndarray, n_classes: int) -> np.ndarray:
    """``(N, K)`` window log-probabilities → ``(K,)``: how many windows rank each class first."""
    return np.bincount(log_probs.argmax(axis=1), minlength=n_classes) if len(log_probs) else np.zeros(n_classes, int)


@dataclass(frozen=True)
class CalibratedAnswer:
    """A session's calibrated answer (``assignment_confidence``)."""

    p_correct: np.ndarray | None  # per sensor the probability that its segment is right (0 for one without)
    p_all_correct: float | None  # that every assigned sensor is right (a model with a session calibration)
    status: str
    committed: np.ndarray | None  # per sensor: sure of its own segment (``ConfidenceModel.committed``)


def assignment_confidence(
    model: ConfidenceModel | None, joint: JointAssignment, votes: np.ndarray, moving: np.ndarray
) -> CalibratedAnswer:
    """A session's calibrated answer: per sensor the probability that its segment is right and whether it is sure
    of it, the probability that all are, and the session's status (``ConfidenceModel.status``); status
    ``uncalibrated`` and no probabilities for a model whose manifest has no ``confidence`` section."""
    if model is None:
        return CalibratedAnswer(None, None, "uncalibrated", None)
    assigned = joint.segment >= 0
    p = np.where(assigned, model.p_correct(confidence_features(joint.segment, joint.margin, votes, moving)), 0.0)
    return CalibratedAnswer(
        p, model.p_all_correct(p, assigned), model.status(p, moving, assigned), model.committed(p, moving, assigned)
    )
