"""Unit conversion to the model contract: acc in m/s², gyr in rad/s (docs/conventions.md)."""

from __future__ import annotations

import numpy as np

STANDARD_GRAVITY_MPS2 = 9.80665  # for converting readings given in g
GRAVITY_MPS2 = 9.81  # world gravity of the simulation and the model's input scale (docs/conventions.md)
ACC_UNITS = {"m/s^2": 1.0, "g": STANDARD_GRAVITY_MPS2}
GYR_UNITS = {"rad/s": 1.0, "deg/s": float(np.pi / 180.0)}


class UnitError(ValueError):
    """An unknown unit name; the message lists the accepted ones."""


def to_contract_units(imu: np.ndarray, acc_unit: str, gyr_unit: str) -> np.ndarray:
    """Scale ``(..., 6)`` readings (acc xyz, gyr xyz) from the given units to m/s² and rad/s."""
    if acc_unit not in ACC_UNITS:
        raise UnitError(f"accelerometer unit must be one of {sorted(ACC_UNITS)}, got {acc_unit!r}")
    if gyr_unit not in GYR_UNITS:
        raise UnitError(f"gyroscope unit must be one of {sorted(GYR_UNITS)}, got {gyr_unit!r}")
    scale = np.array([ACC_UNITS[acc_unit]] * 3 + [GYR_UNITS[gyr_unit]] * 3)
    return np.asarray(imu, dtype=np.float64) * scale


# Plausibility of readings already converted to contract units (docs/conventions.md): what a mistaken unit looks like.
GRAVITY_PLAUSIBLE_MPS2 = (6.0, 14.0)  # |mean specific force| over a 2 s window of human motion: gravity
MAX_HUMAN_GYR_RADS = 35.0  # 2000 deg/s, the full scale of common IMUs; human segments stay below it
UNIT_CHECK_SECONDS = 2.0  # readings are judged over windows this long: long enough for the mean to read gravity


def unit_warnings(imu: np.ndarray, acc_unit: str, gyr_unit: str) -> list[str]:
    """Warnings for windows ``(N, T, 6)`` in m/s² and rad/s whose values are implausible for the declared units.

    Over a window of a couple of seconds a body segment's mean specific force is gravity, whatever it does: a median
    far from 9.81 m/s² means the accelerometer unit is wrong (values in g declared as m/s² read about 1; in m/s²
    declared as g, about 96). A gyroscope beyond 35 rad/s (2000 deg/s) is faster than any human segment turns:
    deg/s declared as rad/s.
    """
    warnings = []
    gravity = float(np.median(np.linalg.norm(imu[..., :3].mean(axis=1), axis=-1)))
    low, high = GRAVITY_PLAUSIBLE_MPS2
    if not low <= gravity <= high:
        guess = "g" if gravity < low else "m/s^2"
        warnings.append(
            f"acc_unit: the windows' mean specific force (gravity) reads {gravity:.3g} m/s² in the declared unit "
            f"{acc_unit!r}, expected about {GRAVITY_MPS2}: are the values in {guess!r}?"
        )
    peak = float(np.linalg.norm(imu[..., 3:6], axis=-1).max())
    if peak > MAX_HUMAN_GYR_RADS:
        warnings.append(
            f"gyr_unit: the gyroscope reads up to {peak:.3g} rad/s in the declared unit {gyr_unit!r}, beyond what a "
            f"human segment turns (about {MAX_HUMAN_GYR_RADS:g} rad/s): are the values in 'deg/s'?"
        )
    return warnings


def unit_warnings_over(readings: np.ndarray, sample_rate_hz: float, acc_unit: str, gyr_unit: str) -> list[str]:
    """``unit_warnings`` over one sensor's readings ``(T, 6)`` in contract units, cut into ``UNIT_CHECK_SECONDS``
    windows; none for fewer readings than one window (too short for the mean to read gravity)."""
    n = int(UNIT_CHECK_SECONDS * sample_rate_hz)
    if n < 1 or len(readings) < n:
        return []
    return unit_warnings(readings[: len(readings) // n * n].reshape(-1, n, readings.shape[-1]), acc_unit, gyr_unit)
