"""Properties of the simulated resistive flex sensor that a real one has (each can fail)."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from training.flex.simulate import (
    ADC_MAX,
    FLEX_RATE_HZ,
    LOT_PARAMS,
    LOT_SPREAD,
    RANGES,
    bend_term,
    counts,
    draw_sensor,
    draw_suit,
    play_operator,
    resistance_ohm,
    simulate_counts,
)

RNG = np.random.default_rng(0)
SENSORS = [draw_sensor(np.random.default_rng(k), lot=k % 2 == 0) for k in range(40)]


@pytest.mark.parametrize("p", SENSORS[:10])
def test_the_static_curve_rises_monotonically_and_bends_upwards(p) -> None:
    theta = np.linspace(0.0, 150.0, 301)
    r = p.r0_ohm * (1.0 + bend_term(theta, p))
    assert np.all(np.diff(r) > 0)
    assert np.all(np.diff(r, 2) >= -1e-9)  # convex: flat near straight, steeper when bent
    assert 2.0 <= r[180] / r[0] <= 4.0 + 1e-9  # the 2-4x at 90° of RANGES["k90"]


@pytest.mark.parametrize("p", SENSORS[:10])
def test_a_bend_and_release_loop_has_hysteresis_with_extension_reading_higher(p) -> None:
    """Flex from 0 to 100° and back: the same angle reads higher on the way back (the play operator lags), so the
    loop (resistance against angle) encloses a positive area when traversed counter-clockwise."""
    p = replace(p, relax_fraction=0.0, baseline_rate_per_min=0.0, gain_rate_per_min=0.0)
    up = np.linspace(0.0, 100.0, 200)
    theta = np.concatenate([up, up[::-1]])
    r = resistance_ohm(theta, p)
    flexing, extending = r[:200], r[200:][::-1]
    assert np.all(extending[20:-20] > flexing[20:-20])
    area = np.trapezoid(extending - flexing, up)
    assert area > 0


def test_the_play_operator_follows_only_beyond_its_half_width() -> None:
    x = np.array([0.0, 2.0, 5.0, 3.0, 1.0, 6.0])
    np.testing.assert_allclose(play_operator(x, 2.0), [0.0, 0.0, 3.0, 3.0, 3.0, 4.0])


def test_a_held_bend_relaxes_by_its_fraction_and_no_more() -> None:
    p = replace(SENSORS[0], relax_fraction=0.05, relax_tau_s=5.0, baseline_rate_per_min=0.0, gain_rate_per_min=0.0)
    theta = np.r_[np.zeros(20), np.full(int(60 * FLEX_RATE_HZ), 90.0)]
    r = resistance_ohm(theta, p)
    bend_part = r / (p.r0_ohm * (1 + p.baseline0)) - 1.0
    assert bend_part[21] > bend_part[-1]  # it relaxes while held
    expected_end = p.gain0 * bend_term(np.array([90.0 * p.placement - p.hysteresis_deg]), p)[0] * (1 - 0.05)
    assert bend_part[-1] == pytest.approx(expected_end, rel=0.02)


def test_counts_are_12_bit_integers_whatever_the_bend() -> None:
    theta = np.random.default_rng(1).uniform(-20.0, 180.0, size=(2000, 4))
    for k in range(5):
        c = simulate_counts(theta, draw_suit(np.random.default_rng(k), 4, lot=False), np.random.default_rng(k))
        assert c.min() >= 0 and c.max() <= ADC_MAX
        np.testing.assert_array_equal(c, np.round(c))


def test_a_straight_sensor_reads_above_zero_and_a_bent_one_below_saturation() -> None:
    """The divider and gain of eq. 1 keep the nominal lot inside the ADC's range: straight above 0, 120° below 4095."""
    for k in range(20):
        p = draw_sensor(np.random.default_rng(k), baseline0=0.0, gain0=1.0, noise_counts=0.0)
        r = resistance_ohm(np.r_[np.zeros(50), np.full(50, 120.0)], replace(p, baseline_rate_per_min=0.0))
        c = counts(r, p, np.random.default_rng(0))
        assert 0 < c[10] and c[-1] < ADC_MAX


def test_ageing_drifts_the_baseline_within_its_stated_range() -> None:
    lo, hi, _ = RANGES["baseline0"]
    rate_hi = RANGES["baseline_rate_per_min"][1]
    minutes = 10
    theta = np.zeros(int(minutes * 60 * FLEX_RATE_HZ))
    for p in SENSORS:
        r = resistance_ohm(theta, p)
        drift = r / p.r0_ohm - 1.0
        assert lo - 1e-9 <= drift[0] <= hi + 1e-9
        assert 0.0 <= drift[-1] - drift[0] <= rate_hi * minutes + 1e-9
        assert np.all(np.diff(drift) >= -1e-12)  # resistance only rises with age (Chen et al. 2024 §3.4.2)


def test_sensors_of_one_lot_stay_within_the_lot_spread_and_replacements_do_not() -> None:
    lot = [draw_sensor(np.random.default_rng(k)) for k in range(200)]
    other = [draw_sensor(np.random.default_rng(k), lot=False) for k in range(200)]
    for name in LOT_PARAMS:
        lo, hi, _ = RANGES[name]
        mid = 0.5 * (lo + hi)
        values = np.array([getattr(p, name) for p in lot])
        assert np.all(np.abs(values / mid - 1.0) <= LOT_SPREAD + 1e-9)
        spread = np.array([getattr(p, name) for p in other])
        assert spread.min() >= lo and spread.max() <= hi and np.ptp(spread) > 2 * LOT_SPREAD * mid


def test_a_replaced_sensor_reads_differently_from_its_replacement_on() -> None:
    theta = np.tile(np.r_[np.linspace(0, 90, 40), np.linspace(90, 0, 40)], 10)[:, None]
    suit = draw_suit(np.random.default_rng(3), 1, baseline0=0.1)
    new = draw_sensor(np.random.default_rng(99), lot=False)
    same = simulate_counts(theta, suit, np.random.default_rng(0))
    swapped = simulate_counts(theta, suit, np.random.default_rng(0), replace_at={0: (400, new)})
    np.testing.assert_array_equal(same[:400], swapped[:400])
    assert np.abs(same[400:] - swapped[400:]).mean() > 20.0
