"""From validated windows to model inputs and results (numpy; no HTTP here)."""

from __future__ import annotations

import math
from functools import lru_cache

import numpy as np

from service.core.resample import resample_uniform
from service.core.rotations import canonical_quat, matrix_from_quat
from service.core.segments import SEGMENTS
from service.core.units import to_contract_units
from service.core.windowing import MODEL_RATE_HZ, WINDOW_SAMPLES

MIN_RATE_HZ, MAX_RATE_HZ = 10.0, 2000.0
# The largest magnitude of a reading in its unit: far beyond what IMUs measure (±16 g and ±2000 °/s are typical
# ranges), small enough that a window cannot overflow float32 on its way through unit conversion and the models.
MAX_ABS_READING = 1e6
# The fewest rows a window can have: at the lowest rate, the rows that resample to 128 at 60 Hz (22).
MIN_WINDOW_ROWS = math.ceil(WINDOW_SAMPLES * MIN_RATE_HZ / MODEL_RATE_HZ)


class InputError(ValueError):
    """A client's input cannot be turned into a model window; the message says why."""


def _rows(samples: list[list[float]], n: int, names: str, where: str) -> np.ndarray:
    """Rows of ``n`` values each → ``(N, n)`` float64; a shorter or longer row is named in the error."""
    bad = next((len(r) for r in samples if len(r) != n), None)
    if bad is not None:
        raise InputError(f"{where}: every sample needs {n} values ({names}), got a row of {bad}")
    return np.asarray(samples, dtype=np.float64)


def _check_finite_and_rate(x: np.ndarray, rate_hz: float, min_rate_hz: float, where: str) -> None:
    """``x`` ``(n, N, C)``; ``where`` may hold ``{i}``, replaced by the offending window's index."""
    finite = np.isfinite(x).reshape(len(x), -1).all(axis=1)
    if not finite.all():
        raise InputError(f"{where.format(i=int(np.argmin(finite)))}: samples must be finite numbers, got NaN or Inf")
    peak = np.abs(x).reshape(len(x), -1).max(axis=1)
    if (peak > MAX_ABS_READING).any():
        i = int(np.argmax(peak > MAX_ABS_READING))
        raise InputError(
            f"{where.format(i=i)}: samples must lie in [-{MAX_ABS_READING:g}, {MAX_ABS_READING:g}] (in their unit), "
            f"got {peak[i]:g}"
        )
    if not min_rate_hz <= rate_hz <= MAX_RATE_HZ:
        raise InputError(
            f"{where.format(i=0)}: sample_rate_hz must be in [{min_rate_hz:g}, {MAX_RATE_HZ:g}], got {rate_hz}"
        )


def window_to_model_input(
    samples: list[list[float]], rate_hz: float, acc_unit: str, gyr_unit: str, where: str
) -> np.ndarray:
    """Rows ``(N, 6)`` in any supported unit and rate → ``(128, 6)`` float32 at 60 Hz, contract units."""
    x = _rows(samples, 6, "acc xyz, gyr xyz", where)
    return windows_to_model_input(x[None], rate_hz, acc_unit, gyr_unit, where)[0]


def windows_to_model_input(x: np.ndarray, rate_hz: float, acc_unit: str, gyr_unit: str, where: str) -> np.ndarray:
    """A stack ``(n, N, 6)`` of windows sharing rate and units → ``(n, 128, 6)`` float32 at 60 Hz.

    ``where`` names the stack in error messages; a ``{i}`` in it is replaced by the offending window's index.
    """
    _check_finite_and_rate(x, rate_hz, MIN_RATE_HZ, where)
    return fit_window(to_contract_units(x, acc_unit, gyr_unit), rate_hz, MODEL_RATE_HZ, WINDOW_SAMPLES, where)


def fit_window(x: np.ndarray, rate_hz: float, model_rate_hz: float, window: int, where: str) -> np.ndarray:
    """Windows ``(n, N, C)`` at ``rate_hz`` → ``(n, window, C)`` float32 at the model's rate.

    At the model's rate a window must have exactly ``window`` samples (another length is a mistake worth
    reporting); at any other rate it is resampled and its last ``window`` samples are used.
    """
    n_samples = x.shape[1]
    if np.isclose(rate_hz, model_rate_hz):
        if n_samples != window:
            raise InputError(
                f"{where.format(i=0)}: at {model_rate_hz:g} Hz a window has {window} samples, got {n_samples}"
            )
        return x.astype(np.float32)
    x = resample_uniform(x.transpose(1, 0, 2), rate_hz, model_rate_hz).transpose(1, 0, 2)
    if x.shape[1] < window:
        need = int(np.ceil(window * rate_hz / model_rate_hz))
        raise InputError(
            f"{where.format(i=0)}: at {rate_hz:g} Hz a window needs at least {need} samples "
            f"({window} after resampling to {model_rate_hz:g} Hz), got {n_samples}"
        )
    return x[:, -window:].astype(np.float32)


def window_results(
    probs: np.ndarray,
    quats: np.ndarray | None,
    moving: np.ndarray,
    turning: np.ndarray,
    segments: list[int | None] | None = None,
) -> list[dict]:
    """Per-window answers shared by REST and streaming, computed for the whole batch at once: class,
    confidence, probabilities, ``moving``, ``turns_about_vertical`` (``turning`` of a moving window) and the
    alignment for the declared segment (``segments[i]``) or else the predicted class."""
    n = len(probs)
    cls = probs.argmax(axis=1)
    alignments: list[dict | None] = [None] * n
    if quats is not None:
        seg = cls if segments is None else np.array([c if s is None else s for c, s in zip(cls, segments, strict=True)])
        q = canonical_quat(quats[np.arange(n), seg])
        R = matrix_from_quat(q).round(7).tolist()
        alignments = [
            {"segment": SEGMENTS[s], "q_segment_imu": qi, "R_segment_imu": Ri}
            for s, qi, Ri in zip(seg.tolist(), q.tolist(), R, strict=True)
        ]
    rows = probs.tolist()
    return [
        {
            "segment": SEGMENTS[c],
            "confidence": row[c],
            "probabilities": dict(zip(SEGMENTS, row, strict=True)),
            "moving": bool(m),
            "turns_about_vertical": bool(m and t),
            "alignment": a,
        }
        for c, row, m, t, a in zip(cls.tolist(), rows, moving, turning, alignments, strict=True)
    ]


MODE_DEG = 45.0  # windows within this of a window count towards its mode (``mean_alignment``)
MODE_CANDIDATES = 64  # windows tried as the start of the robust mean
_MODE_COS_HALF = float(np.cos(np.radians(MODE_DEG) / 2))


def median(x: np.ndarray) -> float:
    """``np.median`` of a 1-D array, the same value (NaN if any is NaN; the mean of the two middle values for an even
    count), two to four times faster on the few hundred values of a stream's alignment windows: a live stream
    computes four per window and sensor (``mean_alignment``)."""
    n = len(x)
    k = n // 2
    part = np.partition(x, (k - 1, k, n - 1) if n % 2 == 0 else (k, n - 1))
    if np.isnan(part[-1]):  # NaN sorts last
        return float("nan")
    return float(part[k] if n % 2 else (part[k - 1] + part[k]) / 2)


@lru_cache(maxsize=512)
def _mode_candidates(n: int) -> np.ndarray:
    """Indices of at most ``MODE_CANDIDATES`` windows spread over ``n``."""
    return np.linspace(0, n - 1, min(n, MODE_CANDIDATES)).astype(int)


def mean_alignment(q_rows: np.ndarray) -> tuple[np.ndarray, float]:
    """Robust rotation mean of window quaternions ``(N, 4)`` → (canonical ``(4,)``, spread in degrees).

    It starts from the window with the most windows within ``MODE_DEG`` of it (of at most ``MODE_CANDIDATES``
    windows spread over the rows), then takes the chordal mean (the top eigenvector of Σ q qᵀ, sign-free; what
    ``scipy``'s ``Rotation.mean`` computes) three times over the windows no farther from the current mean than the
    median, so a minority of windows that disagree (e.g. a 180° turn about the long axis) cannot pull it. Started
    from the chordal mean of all windows instead, two modes a half turn apart in near-equal shares (a real pelvis
    whose walk does not say which way it faces) drew it to a quarter turn between them, neither answer. The spread
    is the median angle of all windows from the result. Plain numpy: streams recompute it as windows arrive.
    """
    q = q_rows / np.linalg.norm(q_rows, axis=1, keepdims=True)

    def chordal_mean(rows: np.ndarray) -> np.ndarray:
        return np.linalg.eigh(rows.T @ rows)[1][:, -1]

    def angles(mean: np.ndarray) -> np.ndarray:
        return 2.0 * np.arccos(np.clip(np.abs(q @ mean), 0.0, 1.0))

    candidates = q[_mode_candidates(len(q))]
    near = np.abs(candidates @ q.T) >= _MODE_COS_HALF  # rotation angle ≤ MODE_DEG
    mean = candidates[int(np.argmax(near.sum(axis=1)))]
    for _ in range(3):
        dist = angles(mean)
        mean = chordal_mean(q[dist <= median(dist)])
    spread = float(np.degrees(median(angles(mean))))
    return canonical_quat(mean), spread


def alignment_answer(segment: int, q: np.ndarray) -> dict:
    """The ``Alignment`` of the API for one segment index and quaternion."""
    return {
        "segment": SEGMENTS[segment],
        "q_segment_imu": q.tolist(),
        "R_segment_imu": matrix_from_quat(q).round(7).tolist(),
    }


REFRESH_SHARE = 16  # a running alignment is recomputed once this share (1/16) of the windows it reads are new


class RunningAlignment:
    """A streamed sensor's alignment: ``mean_alignment`` over its last ``capacity`` moving windows (the same robust
    mean as ``/v1/imu/assign``) for whichever segment the session assigns it to. The quaternions of all seven
    segment hypotheses are kept in a fixed ring (memory is bounded; a sensor that slipped is followed).

    A segment's mean is recomputed once a sixteenth of the windows it reads are new since it was last computed for
    that segment (every new window below 32, every 28th once 450 are in): a robust mean over many windows moves
    little by one more, and recomputing it per window was most of a long stream's running assignment cost.
    ``mean(segment, fresh=True)`` reads every window (a stream's last message)."""

    def __init__(self, capacity: int) -> None:
        self.rows = np.zeros((capacity, len(SEGMENTS), 4), dtype=np.float32)
        self.count = 0  # moving windows ever added
        self._cached: dict[int, tuple[int, np.ndarray, float]] = {}  # segment → (count, q, spread)

    def add(self, q_segments: np.ndarray) -> None:
        """One window's ``(7, 4)`` quaternions."""
        self.rows[self.count % len(self.rows)] = q_segments
        self.count += 1

    def mean(self, segment: int, fresh: bool = False) -> tuple[np.ndarray, float] | None:
        """(canonical quaternion, spread in degrees), or None before the first moving window."""
        if not self.count:
            return None
        in_ring = min(self.count, len(self.rows))
        cached = self._cached.get(segment)
        new = self.count - cached[0] if cached is not None else None
        if new is None or (new > 0 and (fresh or new >= max(1, in_ring // REFRESH_SHARE))):
            q, spread = mean_alignment(self.rows[:in_ring, segment].astype(np.float64))
            self._cached[segment] = cached = (self.count, q, spread)
        return cached[1], cached[2]
