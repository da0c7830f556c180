"""Virtual IMUs on the canonical body and the model's inputs and targets (Zheng et al. 2021 §4.1; TransPose 2021).

A session of one clip draws, per sensor: a sensor-to-segment rotation (uniform over SO(3): the calibration takes
it out), an offset from the segment midpoint, accelerometer and gyroscope bias, and a small error of the
sensor's own orientation fusion; and one heading of the sensors' world frame about the vertical (ENU, NWU, …
differ by such a turn). The sensors' raw readings (``q_world_sensor``, specific force and angular rate in the
sensor frame, 60 Hz) then go through ``service.core.calibration`` exactly as a client's readings do in the
service: declared alignments (with an error) → segment readings → pelvis-relative features.

Acceleration of the sensor's position, two ways (``acc_method``):

- ``finite_difference``: TransPose's smoothed second difference a(t) = (x(t−n) + x(t+n) − 2x(t)) / (nΔt)², n = 4
  at 60 Hz (TransPose `articulate` synthesis);
- ``butterworth``: the I2S pipeline's zero-lag Butterworth (order 8, 10 Hz; Zimmermann et al. 2018 §2.4.2), then a
  central second difference.

``docs/pose.md`` compares them on CMU and Bandai-Namco (``python -m training.cli pose-acc-check``).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from scipy.signal import butter, sosfiltfilt
from scipy.spatial.transform import Rotation

from service.core.body import BODY_SEGMENTS, BodyMotion
from service.core.calibration import pose_features, segment_readings
from service.core.kinematics import body_angular_velocity
from service.core.rotations import quat_from_matrix
from service.core.units import GRAVITY_MPS2


@dataclass(frozen=True)
class SensorNoise:
    """Per-session draws. Ranges: acc noise σ 1 m/s² (Zimmermann et al. 2018 §2.4.2: variance 1 m²/s⁴); acc bias ±0.2
    m/s² and gyro bias ±0.02 rad/s per axis (assumed, MEMS class after factory calibration); gyro noise σ 0.01 rad/s
    (assumed); fusion error of the sensor's own orientation up to 2° tilt and 5° heading per sensor (assumed; Xsens MTw
    spec: 0.75° roll/pitch, 1.5° heading, static); calibration error of the declared alignment up to 5° (assumed);
    sensor offset from the midpoint ±3 cm per axis (assumed)."""

    acc_sigma_mps2: float = 1.0
    acc_bias_mps2: float = 0.2
    gyr_sigma_rads: float = 0.01
    gyr_bias_rads: float = 0.02
    tilt_error_deg: float = 2.0
    heading_error_deg: float = 5.0
    calibration_error_deg: float = 5.0
    offset_m: float = 0.03


_Z = np.array([0.0, 0.0, 1.0])
NO_NOISE = SensorNoise(0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0)


def acceleration(x: np.ndarray, rate_hz: float, method: str = "finite_difference", n: int = 4) -> np.ndarray:
    """Second time derivative of positions ``(T, ..., 3)``."""
    dt = 1.0 / rate_hz
    if method == "finite_difference":
        a = np.zeros_like(x)
        if len(x) > 2 * n:
            a[n:-n] = (x[: -2 * n] + x[2 * n :] - 2.0 * x[n:-n]) / (n * dt) ** 2
            a[:n], a[-n:] = a[n], a[-n - 1]
        return a
    if method == "butterworth":
        if len(x) > 60:
            x = sosfiltfilt(butter(8, 10.0, fs=rate_hz, output="sos"), x, axis=0)
        return np.gradient(np.gradient(x, dt, axis=0), dt, axis=0)
    raise ValueError(f"acc_method must be 'finite_difference' or 'butterworth', got {method!r}")


def _small_rotations(rng: np.random.Generator, n: int, max_deg: float) -> np.ndarray:
    """``n`` rotations about uniform random axes by angles uniform in [0, max_deg]."""
    axis = rng.normal(size=(n, 3))
    axis /= np.linalg.norm(axis, axis=1, keepdims=True)
    return Rotation.from_rotvec(axis * np.radians(rng.uniform(0, max_deg, size=(n, 1)))).as_matrix()


@dataclass(frozen=True)
class RawReadings:
    """What a client's sensors give: ``q_world_sensor`` (T, N, 4), ``acc_mps2`` and ``gyr_rads`` (T, N, 3) in the
    sensor frames, with the true ``q_segment_sensor`` (N, 4) and the world heading ``heading_rad``."""

    q_world_sensor: np.ndarray
    acc_mps2: np.ndarray
    gyr_rads: np.ndarray
    q_segment_sensor: np.ndarray
    heading_rad: float


def simulate_sensors(
    motion: BodyMotion,
    sensor_segments: Sequence[str],
    rng: np.random.Generator,
    noise: SensorNoise = SensorNoise(),
    acc_method: str = "finite_difference",
) -> RawReadings:
    """Raw readings of sensors on ``sensor_segments`` for one session of ``motion``."""
    idx = [BODY_SEGMENTS.index(s) for s in sensor_segments]
    N, rate = len(idx), motion.sample_rate_hz
    R_seg = motion.R_world_segment[:, idx]  # (T, N, 3, 3)
    R_seg_sensor = Rotation.random(N, random_state=rng).as_matrix()
    R_ws = np.einsum("tnij,njk->tnik", R_seg, R_seg_sensor)
    offset = rng.uniform(-noise.offset_m, noise.offset_m, size=(N, 3))
    pos = motion.midpoint_m[:, idx] + np.einsum("tnij,nj->tni", R_seg, offset)
    acc_world = acceleration(pos, rate, acc_method) + np.array([0.0, 0.0, GRAVITY_MPS2])
    acc = np.einsum("tnji,tnj->tni", R_ws, acc_world)
    acc += (
        rng.uniform(-noise.acc_bias_mps2, noise.acc_bias_mps2, (N, 3))
        + rng.normal(0, 1, acc.shape) * noise.acc_sigma_mps2
    )
    gyr = np.stack([body_angular_velocity(R_ws[:, k], rate) for k in range(N)], axis=1)
    gyr += (
        rng.uniform(-noise.gyr_bias_rads, noise.gyr_bias_rads, (N, 3))
        + rng.normal(0, 1, gyr.shape) * noise.gyr_sigma_rads
    )
    # The sensor's fusion: tilt and heading errors per sensor, then the world frame's own heading.
    heading_err = np.radians(rng.uniform(-noise.heading_error_deg, noise.heading_error_deg, N))
    err = _small_rotations(rng, N, noise.tilt_error_deg) @ Rotation.from_rotvec(np.outer(heading_err, _Z)).as_matrix()
    heading = float(rng.uniform(-np.pi, np.pi))
    Rz = Rotation.from_rotvec(heading * _Z).as_matrix()
    R_reported = np.einsum("ij,njk,tnkl->tnil", Rz, err, R_ws)
    return RawReadings(quat_from_matrix(R_reported), acc, gyr, quat_from_matrix(R_seg_sensor), heading)


def declared_alignment(readings: RawReadings, rng: np.random.Generator, error_deg: float) -> np.ndarray:
    """The true ``q_segment_sensor`` with a calibration error of up to ``error_deg`` (a client's declaration)."""
    from service.core.rotations import matrix_from_quat

    R = matrix_from_quat(readings.q_segment_sensor)
    return quat_from_matrix(_small_rotations(rng, len(R), error_deg) @ R)


def root_relative_targets(motion: BodyMotion, output_segments: Sequence[str]) -> np.ndarray:
    """R_root_segment ``(T, S_out, 3, 3)`` of the true motion (Zheng et al. 2021 eq. 2)."""
    idx = [BODY_SEGMENTS.index(s) for s in output_segments]
    R = motion.R_world_segment
    return np.einsum("tji,tsjk->tsik", R[:, 0], R[:, idx])


@dataclass(frozen=True)
class Session:
    """One simulated session: features (T, F) float32, targets (T, S_out, 3, 3), the calibrated segment orientations
    of the sensors (T, N, 3, 3) in the sensors' world frame, and that frame's heading."""

    features: np.ndarray
    targets: np.ndarray
    R_world_sensor_segment: np.ndarray
    heading_rad: float


def simulate_session(
    motion: BodyMotion,
    sensor_segments: Sequence[str],
    output_segments: Sequence[str],
    rng: np.random.Generator,
    noise: SensorNoise = SensorNoise(),
    acc_method: str = "finite_difference",
) -> Session:
    """Raw readings → declared calibration → features, and the targets; the service's path exactly."""
    if sensor_segments[0] != "Pelvis":
        raise ValueError(f"the first sensor must be on the Pelvis (the features' root), got {sensor_segments[0]}")
    raw = simulate_sensors(motion, sensor_segments, rng, noise, acc_method)
    q_seg_sensor = declared_alignment(raw, rng, noise.calibration_error_deg)
    R_w_seg, a_w = segment_readings(raw.q_world_sensor, raw.acc_mps2, q_seg_sensor)
    return Session(
        pose_features(R_w_seg, a_w),
        root_relative_targets(motion, output_segments).astype(np.float32),
        R_w_seg,
        raw.heading_rad,
    )


def acceleration_check(clips: list, segments: Sequence[str] = ("LeftLowerLeg", "LeftForeArm", "Pelvis")) -> dict:
    """Both acceleration methods on the same clips' segment midpoints (world frame, gravity excluded), per source:
    the RMS difference between them, and per method the median and 95th percentile of |a| and the share of the
    signal power above 5 Hz. ``clips``: ``training.pose.data.MotionClip`` at 60 Hz."""
    from collections import defaultdict

    idx = [BODY_SEGMENTS.index(s) for s in segments]
    acc: dict[str, dict[str, list[np.ndarray]]] = defaultdict(lambda: defaultdict(list))
    for c in clips:
        x = c.motion.midpoint_m[:, idx]
        if len(x) < 128:
            continue
        source = "bandai_namco" if c.source.startswith("bandai") else "cmu"
        for method in ("finite_difference", "butterworth"):
            acc[source][method].append(acceleration(x, c.motion.sample_rate_hz, method)[8:-8])
    out = {}
    for source, by_method in acc.items():
        fd, bw = np.concatenate(by_method["finite_difference"]), np.concatenate(by_method["butterworth"])
        row = {"frames": int(len(fd)), "rms_difference_mps2": float(np.sqrt(np.mean((fd - bw) ** 2)))}
        for method, arrays in by_method.items():
            norm = np.linalg.norm(np.concatenate(arrays), axis=-1)
            high = []
            for a in arrays:
                spec = np.abs(np.fft.rfft(a - a.mean(0), axis=0)) ** 2
                f = np.fft.rfftfreq(len(a), 1 / 60.0)
                high.append(spec[f > 5.0].sum() / max(spec.sum(), 1e-12))
            row[method] = {
                "median_mps2": float(np.median(norm)),
                "p95_mps2": float(np.percentile(norm, 95)),
                "power_above_5hz": float(np.mean(high)),
            }
        out[source] = row
    return out
