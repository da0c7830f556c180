"""Resistive flex sensors over the knees and elbows, simulated from the bend of the joints (Chen et al. 2024 §3.2).

Per sensor, from the bend angle θ (degrees, ``service.core.flex.bend_angles_deg``) to 12-bit counts:

1. placement: the strip feels κ·θ (it sits in a pocket and slides a little);
2. hysteresis: a play (backlash) operator of half-width w on the angle, so flexion reads lower than extension at
   the same angle (Chen et al. 2024 Fig. 3b: the flexion and extension curves differ);
3. resistance: R = R0·(1 + β(t)) · (1 + γ(t)·(k − 1)·(θ_p/90°)^p · (1 − a·relax)), monotonic and convex in θ;
   ``relax`` is θ's bend term low-passed with time constant τ: held bent, the reading relaxes by a fraction a;
4. ageing: the baseline β(t) = β0 + β̇·t grows (Chen et al. 2024 §3.4.2: resistance and baseline rise with use)
   and the gain γ(t) = γ0 + γ̇·t drifts; a replaced sensor is a fresh draw of every parameter with β = 0;
5. read-out, Chen et al. 2024 eq. 1: V = (Vcc·R/(Ri + R) − Vcc/2)·G, an ADC of 12 bits over [0, Vcc] at 20 Hz,
   Gaussian noise, rounded and clipped to 0..4095.

Every range and its source is in ``RANGES``. A suit is made of one production lot: the sensor's own curve
(``LOT_PARAMS``: flat resistance, bend ratio, exponent, hysteresis, relaxation) varies within ``LOT_SPREAD`` of
the datasheet's nominal sensor, while how the suit is worn and has aged (placement, ageing, noise) is drawn
over its whole range per session (``draw_suit``). A replaced sensor, or a suit of another lot, is drawn over the
datasheet's whole tolerance (``draw_sensor(lot=False)``): no model can tell a stiff new sensor from a deeper
bend without a calibration, and the robustness tests show what that costs.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
from scipy.signal import lfilter

FLEX_RATE_HZ = 20.0  # Chen et al. 2024 §3.2: the board samples every 0.05 s
ADC_MAX = 4095
VCC = 3.3
DIVIDER_OHM = 15_000.0  # R_i of eq. 1: below the smallest flat resistance, so a straight sensor reads above 0
AMP_GAIN = 2.3  # G of eq. 1: the nominal sensor fully bent (150°) reads about 3,900 counts

# (low, high, source) of each parameter, drawn uniformly per sensor.
RANGES: dict[str, tuple[float, float, str]] = {
    "r0_ohm": (17_500.0, 32_500.0, "Spectra Symbol flex sensor datasheet: flat resistance 25 kΩ ± 30 %"),
    "k90": (2.0, 4.0, "bent to 90° the resistance is 2-4x the flat value (Spectra Symbol: 45-125 kΩ bent)"),
    "exponent": (1.2, 2.0, "assumed: convex curve, flat near straight (Chen et al. 2024 Fig. 3b)"),
    "hysteresis_deg": (1.0, 6.0, "assumed: half-width of the play operator (Chen et al. 2024 Fig. 3b)"),
    "relax_fraction": (0.01, 0.06, "assumed: share of the bend term lost while held bent (polymer-ink creep)"),
    "relax_tau_s": (3.0, 20.0, "assumed: time constant of that relaxation"),
    "placement": (0.92, 1.0, "assumed: the share of the joint's bend the strip in its pocket feels"),
    "baseline0": (0.0, 0.15, "assumed: accumulated ageing at the session's start, share of R0 (training range)"),
    "baseline_rate_per_min": (0.0, 0.03, "assumed: baseline drift within the session, share of R0 per minute"),
    "gain0": (0.95, 1.05, "assumed: sensitivity of the bend term against the new sensor"),
    "gain_rate_per_min": (-0.02, 0.02, "assumed: sensitivity drift per minute"),
    "divider_tol": (-0.01, 0.01, "1 % resistor tolerance on R_i"),
    "amp_tol": (-0.02, 0.02, "assumed: 2 % amplifier gain tolerance"),
    "noise_counts": (1.0, 6.0, "assumed: read-out noise, standard deviation in counts"),
}
# The sensor's own curve: within one production lot each varies by LOT_SPREAD (relative, assumed; the datasheet's
# ±30 % is the tolerance across lots) about the middle of its range.
LOT_PARAMS = ("r0_ohm", "k90", "exponent", "hysteresis_deg", "relax_fraction", "relax_tau_s")
LOT_SPREAD = 0.05
# Ageing beyond the training range, for the robustness curves: baseline shares of R0 at the session's start.
AGEING_BEYOND = (0.0, 0.1, 0.2, 0.3, 0.45, 0.6)


@dataclass(frozen=True)
class SensorParams:
    r0_ohm: float
    k90: float
    exponent: float
    hysteresis_deg: float
    relax_fraction: float
    relax_tau_s: float
    placement: float
    baseline0: float
    baseline_rate_per_min: float
    gain0: float
    gain_rate_per_min: float
    divider_tol: float
    amp_tol: float
    noise_counts: float


def draw_sensor(rng: np.random.Generator, lot: bool = True, **fixed: float) -> SensorParams:
    """One sensor as worn in one session: its curve from the nominal lot (``lot``) or from the datasheet's whole
    tolerance, the session's parameters over their ranges; ``fixed`` overrides any of them."""
    values = {}
    for k, (lo, hi, _) in RANGES.items():
        if lot and k in LOT_PARAMS:
            mid = 0.5 * (lo + hi)
            values[k] = float(rng.uniform(mid * (1 - LOT_SPREAD), mid * (1 + LOT_SPREAD)))
        else:
            values[k] = float(rng.uniform(lo, hi))
    return SensorParams(**(values | fixed))


def draw_suit(rng: np.random.Generator, n_sensors: int, lot: bool = True, **fixed: float) -> list[SensorParams]:
    return [draw_sensor(rng, lot, **fixed) for _ in range(n_sensors)]


def play_operator(theta: np.ndarray, half_width: float) -> np.ndarray:
    """Backlash: the output follows the input only once it is more than ``half_width`` away (rate-independent
    hysteresis; on a loop the output lags behind in both directions). Starts at ``theta[0]``."""
    out = np.empty_like(theta)
    y = theta[0]
    for t, x in enumerate(theta):
        y = min(max(y, x - half_width), x + half_width)
        out[t] = y
    return out


def bend_term(theta_deg: np.ndarray, p: SensorParams) -> np.ndarray:
    """(k − 1)·(θ/90°)^p, monotonic in θ ≥ 0 (negative bends read as straight)."""
    return (p.k90 - 1.0) * (np.clip(theta_deg, 0.0, None) / 90.0) ** p.exponent


def resistance_ohm(theta_deg: np.ndarray, p: SensorParams, rate_hz: float = FLEX_RATE_HZ) -> np.ndarray:
    """Steps 1-4 of the module docstring for one sensor's bend angles at ``rate_hz``."""
    theta = play_operator(p.placement * np.asarray(theta_deg, np.float64), p.hysteresis_deg)
    bend = bend_term(theta, p)
    alpha = 1.0 - np.exp(-1.0 / (rate_hz * p.relax_tau_s))
    relax = lfilter([alpha], [1.0, alpha - 1.0], bend, zi=[bend[0] * (1.0 - alpha)])[0]  # first-order low-pass
    minutes = np.arange(len(theta)) / rate_hz / 60.0
    baseline = p.baseline0 + p.baseline_rate_per_min * minutes
    gain = p.gain0 + p.gain_rate_per_min * minutes
    return p.r0_ohm * (1.0 + baseline) * (1.0 + gain * (bend - p.relax_fraction * relax))


def counts(resistance: np.ndarray, p: SensorParams, rng: np.random.Generator) -> np.ndarray:
    """Chen et al. 2024 eq. 1 into a 12-bit ADC over [0, Vcc], with noise; integers 0..4095 as float32."""
    r_i = DIVIDER_OHM * (1.0 + p.divider_tol)
    v = (VCC * resistance / (r_i + resistance) - VCC / 2.0) * AMP_GAIN * (1.0 + p.amp_tol)
    c = v / VCC * (ADC_MAX + 1) + rng.normal(0.0, p.noise_counts, size=v.shape)
    return np.clip(np.round(c), 0, ADC_MAX).astype(np.float32)


def simulate_counts(
    bend_deg: np.ndarray,
    suit: list[SensorParams],
    rng: np.random.Generator,
    replace_at: dict[int, tuple[int, SensorParams]] | None = None,
    rate_hz: float = FLEX_RATE_HZ,
) -> np.ndarray:
    """``(T, S)`` bend angles → ``(T, S)`` counts for one suit; ``replace_at`` {sensor: (sample, new params)}
    swaps that sensor for another from that sample on (a fresh sensor: its own curve, no ageing yet)."""
    out = np.empty(bend_deg.shape, np.float32)
    for s, p in enumerate(suit):
        r = resistance_ohm(bend_deg[:, s], p, rate_hz)
        if replace_at and s in replace_at:
            t0, new = replace_at[s]
            r[t0:] = resistance_ohm(bend_deg[t0:, s], replace(new, baseline0=0.0), rate_hz)
        out[:, s] = counts(r, p, rng)
    return out
