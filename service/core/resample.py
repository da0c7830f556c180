"""Resampling sensor streams to the model rate (60 Hz) — one implementation for training and serving."""

from __future__ import annotations

from fractions import Fraction

import numpy as np
from scipy.signal import resample_poly


def resample_uniform(x: np.ndarray, from_hz: float, to_hz: float, max_denominator: int = 1000) -> np.ndarray:
    """Polyphase resampling along the first axis of a uniformly sampled stream ``(T, ...)`` (anti-aliased)."""
    if np.isclose(from_hz, to_hz):
        return np.asarray(x, dtype=np.float64)
    ratio = Fraction(to_hz / from_hz).limit_denominator(max_denominator)
    return resample_poly(np.asarray(x, dtype=np.float64), ratio.numerator, ratio.denominator, axis=0, padtype="line")


def interp_along_time(t_new: np.ndarray, t_old: np.ndarray, a: np.ndarray) -> np.ndarray:
    """Linear interpolation of ``(T, ...)`` samples taken at ``t_old`` onto ``t_new``; ``(T', ...)``."""
    flat = a.reshape(a.shape[0], -1)
    out = np.stack([np.interp(t_new, t_old, flat[:, k]) for k in range(flat.shape[1])], axis=1)
    return out.reshape((len(t_new),) + a.shape[1:])


def resample_timestamps(t_s: np.ndarray, x: np.ndarray, to_hz: float) -> tuple[np.ndarray, np.ndarray]:
    """Linear interpolation of an irregularly sampled stream onto a uniform grid; ``(T',)``, ``(T', C)``."""
    grid = np.arange(t_s[0], t_s[-1] + 1e-12, 1.0 / to_hz)
    return grid, interp_along_time(grid, t_s, x)
