"""Where to put N sensors: Zheng et al. 2021 §6 (eq. 14–19), Max-Relevance and Min-Redundancy over the maximal
information coefficient between the candidate positions' measurements.

A position's measurements are what a pose model reads from a sensor there (eq. 2–3, ``service.core.calibration``):
for a segment other than the pelvis its rotation relative to the pelvis (9 numbers) and its acceleration relative to
the pelvis's, in the pelvis frame (3); for the pelvis its up vector and its own acceleration (6). The pelvis is always
chosen first, since every other measurement is relative to it (§6.1).

- eq. 14, MIC(x; y) = max over grids of a × b cells (a·b < B, B = n^0.6) of I(x; y) / log2 min(a, b).
- eq. 15, Rele(X; Y): the MICs between the measurements of positions X and Y.
- eq. 16–18: T(S, C), the mean relevance between the chosen positions S and the others C; R(S), the mean relevance
  among the chosen ones; Φ = T − R, logged for each placement size.
- eq. 19: greedily, the position x whose mean relevance to the positions still unchosen (x itself left out) minus
  its mean relevance to the chosen ones is the largest: the incremental form of Max-Relevance and Min-Redundancy
  (Peng et al. 2005, the paper's ref. 45).

Where this departs from the paper:

- MIC's grids are equal-frequency on both axes, a and b from 2 to ⌊√B⌋: every grid of that size at once, for every
  pair of measurements, as one matrix product of indicator matrices per grid. Reshef et al. (2011) optimise one
  axis's partition for each grid (ApproxMaxMI) and allow long thin grids up to a·b < B; equal-frequency partitions
  give a lower bound on each grid's best mutual information, so these MICs are at most Reshef et al.'s.
- Rele is the mean of the MICs over the pairs of measurements rather than their sum: the pelvis has 6 measurements
  and the other positions 12, and a sum would make the pelvis look half as relevant. With equal numbers of
  measurements, as in the paper, the two differ by a constant factor, and the greedy choice does not change.
- Eq. 19 as printed garbles its indices (the relevance term sums over the chosen positions, the redundancy over pairs
  of chosen positions, neither naming the candidate); we read it as Peng et al.'s incremental criterion, which it
  adapts, with eq. 16–17's means. R leaves out the pairs of a position with itself (eq. 17 sums over all pairs):
  with them, a position whose own measurements depend on each other less (a hand's free rotation) is preferred for
  that alone, which says nothing about how well it tells the other positions.
- Toes are no candidate: a sensor is not worn on a toe (the foot carries it).
- The frames are a random sample of the training clips, drawn with the training's share of Bandai-Namco, not all of
  them: consecutive frames carry little new information, and the cost grows with their number.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field

import numpy as np

from service.core.body import BODY_SEGMENTS
from service.core.calibration import pose_features
from training.data.catalog import is_bandai_namco
from training.pose.data import MotionClip
from training.pose.simulate import acceleration

log = logging.getLogger(__name__)

ROOT = "Pelvis"
CANDIDATES: tuple[str, ...] = tuple(s for s in BODY_SEGMENTS if not s.endswith("Toe"))


def measurements(clip: MotionClip, positions: tuple[str, ...] = CANDIDATES) -> np.ndarray:
    """(T, F): the measurements of a sensor at each position in ``positions`` (the first must be the pelvis), in the
    layout of ``service.core.calibration.pose_features``: 6 for the pelvis, then 12 per other position. Noise-free:
    the segments' own rotations and the accelerations of their midpoints (the training's finite difference)."""
    if positions[0] != ROOT:
        raise ValueError(f"the first position must be {ROOT}, got {positions[0]}")
    m = clip.motion
    index = [BODY_SEGMENTS.index(p) for p in positions]
    acc = acceleration(m.midpoint_m[:, index], m.sample_rate_hz)
    return pose_features(m.R_world_segment[:, index], acc)


def measurement_groups(positions: tuple[str, ...]) -> list[slice]:
    """Columns of each position in ``measurements``: 6 for the pelvis, then 12 each."""
    return [slice(0, 6)] + [slice(6 + 12 * k, 18 + 12 * k) for k in range(len(positions) - 1)]


def _ranks(x: np.ndarray) -> np.ndarray:
    """(n, F) rank of every value in its column, ties broken at random (a fixed draw): a constant column then
    falls into random bins and tells nothing, instead of following the samples' order."""
    shuffle = np.random.default_rng(0).permutation(len(x))
    ranks = np.empty(x.shape, np.int64)
    order = shuffle[np.argsort(x[shuffle], axis=0, kind="stable")]  # (n, F): sample indices in rank order
    ranks[order, np.arange(x.shape[1])[None, :]] = np.arange(len(x))[:, None]
    return ranks


def _bins(ranks: np.ndarray, k: int) -> np.ndarray:
    """(n, F) equal-frequency bin of every value among ``k``."""
    return (ranks * k) // len(ranks)


def _indicators(bins: np.ndarray, k: int) -> np.ndarray:
    """(n, F·k) one-hot rows: column f·k + b is 1 where measurement f falls in bin b."""
    n, f = bins.shape
    out = np.zeros((n, f * k), np.float32)
    out[np.arange(n)[:, None], np.arange(f)[None, :] * k + bins] = 1.0
    return out


def mic_matrix(x: np.ndarray, max_cells: float | None = None) -> np.ndarray:
    """(F, F) maximal information coefficient (eq. 14) between every pair of columns of ``x`` (n, F), on
    equal-frequency grids of a × b cells with 2 ≤ a, b ≤ ⌊√B⌋, B = n^0.6 (module docstring)."""
    n, f = x.shape
    budget = n**0.6 if max_cells is None else max_cells
    side = int(np.sqrt(budget))
    if side < 2:
        raise ValueError(f"{n} samples allow no grid of 2 × 2 cells (B = n^0.6 = {budget:.1f})")
    ranks = _ranks(x)
    indicators = {k: _indicators(_bins(ranks, k), k) for k in range(2, side + 1)}
    best = np.zeros((f, f))
    for a in range(2, side + 1):
        for b in range(a, side + 1):
            p = (indicators[a].T @ indicators[b]).reshape(f, a, f, b) / n  # joint cell frequencies
            px, py = p.sum(3, keepdims=True), p.sum(1, keepdims=True)
            with np.errstate(divide="ignore", invalid="ignore"):
                terms = np.where(p > 0, p * np.log2(p / (px * py)), 0.0)
            mi = terms.sum(axis=(1, 3)) / np.log2(min(a, b))  # (F, F): rows on the a-grid, columns on the b-grid
            best = np.maximum(best, np.maximum(mi, mi.T))
    return best


def relevance(mic: np.ndarray, groups: list[slice]) -> np.ndarray:
    """(P, P) Rele of eq. 15 between positions: the mean MIC over their pairs of measurements (module docstring)."""
    return np.array([[mic[g, h].mean() for h in groups] for g in groups])


def phi(rele: np.ndarray, chosen: list[int]) -> float:
    """Eq. 18, Φ = T − R: T (eq. 16) the mean relevance between the chosen and the other positions, R (eq. 17) the
    mean relevance between distinct chosen positions (0 for one)."""
    others = [k for k in range(len(rele)) if k not in chosen]
    t = rele[np.ix_(chosen, others)].mean() if others else 0.0
    among = rele[np.ix_(chosen, chosen)]
    r = (among.sum() - np.trace(among)) / (len(chosen) * (len(chosen) - 1)) if len(chosen) > 1 else 0.0
    return float(t - r)


def mrmr_gain(rele: np.ndarray, chosen: list[int], candidate: int) -> float:
    """Eq. 19 (incremental mRMR): the candidate's mean relevance to the positions still unchosen, minus its mean
    relevance to the chosen ones."""
    others = [k for k in range(len(rele)) if k not in chosen and k != candidate]
    relevant = rele[candidate, others].mean() if others else 0.0
    return float(relevant - rele[candidate, chosen].mean())


@dataclass
class Placement:
    """The greedy order: ``order[:n]`` is the placement for n sensors, ``phi[n - 1]`` its Φ (eq. 18) and
    ``gain[n - 1]`` the eq. 19 score its last position was chosen by (none for the pelvis)."""

    positions: tuple[str, ...]
    relevance: np.ndarray  # (P, P) Rele of eq. 15, in ``positions`` order
    order: list[str] = field(default_factory=list)
    phi: list[float] = field(default_factory=list)
    gain: list[float | None] = field(default_factory=list)


def greedy_placement(rele: np.ndarray, positions: tuple[str, ...], n: int) -> Placement:
    """Eq. 19: the pelvis first (§6.1), then each time the position with the largest incremental mRMR score."""
    chosen = [positions.index(ROOT)]
    out = Placement(positions, rele, [ROOT], [phi(rele, chosen)], [None])
    while len(chosen) < min(n, len(positions)):
        scores = {k: mrmr_gain(rele, chosen, k) for k in range(len(positions)) if k not in chosen}
        best = max(scores, key=scores.__getitem__)
        chosen.append(best)
        out.order.append(positions[best])
        out.phi.append(phi(rele, chosen))
        out.gain.append(scores[best])
    return out


def sample_frames(clips: list[MotionClip], n: int, bandai_share: float | None, rng: np.random.Generator) -> np.ndarray:
    """(n, F) measurements of ``n`` frames drawn at random from ``clips`` (each frame equally likely within its
    group), ``bandai_share`` of them from Bandai-Namco (None: in proportion to the frames)."""
    bandai = [c for c in clips if is_bandai_namco(c.source)]
    other = [c for c in clips if not is_bandai_namco(c.source)]
    if bandai_share is None or not bandai or not other:
        groups = [(clips, n)]
    else:
        k = int(round(n * bandai_share))
        groups = [(bandai, k), (other, n - k)]
    rows = []
    for group, count in groups:
        sizes = np.array([c.motion.n_frames for c in group], float)
        picks = rng.choice(len(group), size=count, p=sizes / sizes.sum())
        for clip_index in np.unique(picks):
            m = measurements(group[clip_index])
            rows.append(m[rng.integers(0, len(m), size=int(np.sum(picks == clip_index)))])
    return np.concatenate(rows)


def search_placement(
    clips: list[MotionClip], n_sensors: int, frames: int, bandai_share: float | None, seed: int
) -> tuple[Placement, np.ndarray]:
    """The greedy placement of ``n_sensors`` over ``CANDIDATES`` from ``frames`` random frames of ``clips``, and
    the MIC matrix of the measurements it rests on."""
    x = sample_frames(clips, frames, bandai_share, np.random.default_rng(seed))
    log.info("placement: MIC between %d measurements over %d frames", x.shape[1], len(x))
    mic = mic_matrix(x)
    rele = relevance(mic, measurement_groups(CANDIDATES))
    return greedy_placement(rele, CANDIDATES, n_sensors), mic
