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


def resample_quats(q_wxyz: np.ndarray, from_hz: float, to_hz: float = 60.0) -> np.ndarray:
    """Orientations ``(T, 4)`` (w, x, y, z) onto a uniform ``to_hz`` grid by slerp, w >= 0."""
    from scipy.spatial.transform import Rotation, Slerp

    t = np.arange(len(q_wxyz)) / from_hz
    grid = np.minimum(np.arange(0.0, t[-1] + 1e-9, 1.0 / to_hz), t[-1])  # arange may overshoot by rounding
    q = Slerp(t, Rotation.from_quat(q_wxyz, scalar_first=True))(grid).as_quat(scalar_first=True)
    return np.where(q[:, :1] < 0, -q, q)


def resample_pose_rows(
    acc: np.ndarray, gyr: np.ndarray, q_wxyz: np.ndarray, from_hz: float, to_hz: float = 60.0
) -> np.ndarray:
    """A sensor's acc, gyr and orientation onto a uniform ``to_hz`` grid: rows of 10 values (acc xyz, gyr xyz,
    q w x y z), linear for the vectors and slerp for the orientation; what a pose stream sends."""
    q = resample_quats(q_wxyz, from_hz, to_hz)
    t = np.arange(len(acc)) / from_hz
    grid = np.arange(len(q)) / to_hz
    return np.concatenate([interp_along_time(grid, t, acc), interp_along_time(grid, t, gyr), q], axis=1)
