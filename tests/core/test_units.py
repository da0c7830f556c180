"""Unit conversion and the plausibility warnings of a declared unit, on simulated walking-like windows."""

from __future__ import annotations

import numpy as np
import pytest

from service.core.units import GRAVITY_MPS2, STANDARD_GRAVITY_MPS2, to_contract_units, unit_warnings


def _walking(n: int = 6, seed: int = 0) -> np.ndarray:
    """``(n, 128, 6)`` in m/s² and rad/s: gravity along a tilting z plus swing accelerations, a 1 Hz leg swing of
    up to 5 rad/s."""
    rng = np.random.default_rng(seed)
    t = np.arange(128) / 60.0
    x = np.zeros((n, 128, 6))
    x[..., 2] = GRAVITY_MPS2 + 3.0 * np.sin(2 * np.pi * 2 * t)
    x[..., 0] = 4.0 * np.sin(2 * np.pi * t + rng.uniform(0, 6, (n, 1)))
    x[..., 4] = 5.0 * np.sin(2 * np.pi * t)
    return x + rng.normal(scale=0.1, size=x.shape)


def test_plausible_windows_get_no_warning() -> None:
    assert unit_warnings(_walking(), "m/s^2", "rad/s") == []


@pytest.mark.parametrize(
    ("scale_acc", "scale_gyr", "declared", "fragment"),
    [
        (1 / STANDARD_GRAVITY_MPS2, 1.0, ("m/s^2", "rad/s"), "are the values in 'g'"),  # g sent as m/s²
        (STANDARD_GRAVITY_MPS2, 1.0, ("g", "rad/s"), "are the values in 'm/s^2'"),  # m/s² sent as g
        (1.0, 180 / np.pi, ("m/s^2", "rad/s"), "are the values in 'deg/s'"),  # deg/s sent as rad/s
    ],
)
def test_a_wrong_declared_unit_is_named(scale_acc: float, scale_gyr: float, declared, fragment: str) -> None:
    raw = _walking() * np.array([scale_acc] * 3 + [scale_gyr] * 3)
    # What the service sees: the raw numbers converted with the declared units.
    warnings = unit_warnings(to_contract_units(raw, *declared), *declared)
    assert len(warnings) == 1 and fragment in warnings[0], warnings
