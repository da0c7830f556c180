"""From validated windows to model inputs and results (numpy; no HTTP here)."""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from service.core.resample import resample_uniform
from service.core.rotations import canonical_quat, matrix_from_quat
from service.core.segments import SEGMENTS
from service.core.units import to_contract_units
from service.core.windowing import MODEL_RATE_HZ, WINDOW_SAMPLES

MIN_RATE_HZ, MAX_RATE_HZ = 10.0, 2000.0


class InputError(ValueError):
    """A client's input cannot be turned into a model window; the message says why."""


def window_to_model_input(
    samples: list[list[float]], rate_hz: float, acc_unit: str, gyr_unit: str, where: str
) -> np.ndarray:
    """Rows ``(N, 6)`` in any supported unit and rate → ``(128, 6)`` float32 at 60 Hz, contract units."""
    bad = next((len(r) for r in samples if len(r) != 6), None)
    if bad is not None:
        raise InputError(f"{where}: every sample needs 6 values (acc xyz, gyr xyz), got a row of {bad}")
    return windows_to_model_input(np.asarray(samples, dtype=np.float64)[None], rate_hz, acc_unit, gyr_unit, where)[0]


def windows_to_model_input(x: np.ndarray, rate_hz: float, acc_unit: str, gyr_unit: str, where: str) -> np.ndarray:
    """A stack ``(n, N, 6)`` of windows sharing rate and units → ``(n, 128, 6)`` float32 at 60 Hz.

    ``where`` names the stack in error messages; a ``{i}`` in it is replaced by the offending window's index.
    """
    finite = np.isfinite(x).reshape(len(x), -1).all(axis=1)
    if not finite.all():
        raise InputError(f"{where.format(i=int(np.argmin(finite)))}: samples must be finite numbers, got NaN or Inf")
    if not MIN_RATE_HZ <= rate_hz <= MAX_RATE_HZ:
        raise InputError(
            f"{where.format(i=0)}: sample_rate_hz must be in [{MIN_RATE_HZ}, {MAX_RATE_HZ}], got {rate_hz}"
        )
    x = to_contract_units(x, acc_unit, gyr_unit)
    n_samples = x.shape[1]
    if np.isclose(rate_hz, MODEL_RATE_HZ):
        if n_samples != WINDOW_SAMPLES:
            raise InputError(f"{where.format(i=0)}: at 60 Hz a window has {WINDOW_SAMPLES} samples, got {n_samples}")
        return x.astype(np.float32)
    x = resample_uniform(x.transpose(1, 0, 2), rate_hz, MODEL_RATE_HZ).transpose(1, 0, 2)
    if x.shape[1] < WINDOW_SAMPLES:
        need = int(np.ceil(WINDOW_SAMPLES * rate_hz / MODEL_RATE_HZ))
        raise InputError(
            f"{where.format(i=0)}: at {rate_hz} Hz a window needs at least {need} samples "
            f"({WINDOW_SAMPLES} after resampling to 60 Hz), got {n_samples}"
        )
    return x[:, -WINDOW_SAMPLES:].astype(np.float32)


def window_results(
    probs: np.ndarray, quats: np.ndarray | None, moving: np.ndarray, segments: list[int | None] | None = None
) -> list[dict]:
    """Per-window answers shared by REST and streaming, computed for the whole batch at once: class,
    confidence, probabilities, ``moving`` and the alignment for the declared segment (``segments[i]``)
    or else the predicted class."""
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
            "alignment": a,
        }
        for c, row, m, a in zip(cls.tolist(), rows, moving, alignments, strict=True)
    ]


def mean_alignment(q_rows: np.ndarray) -> np.ndarray:
    """Rotation mean of window quaternions ``(N, 4)`` → ``(4,)`` canonical."""
    mean = Rotation.from_quat(q_rows, scalar_first=True).mean().as_quat(scalar_first=True)
    return canonical_quat(mean)
