"""Unit conversion to the model contract: acc in m/s², gyr in rad/s (DESIGN.md §2)."""

from __future__ import annotations

import numpy as np

STANDARD_GRAVITY_MPS2 = 9.80665  # for converting readings given in g
GRAVITY_MPS2 = 9.81  # world gravity of the simulation and the model's input scale (DESIGN.md §2)
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
