"""Readers of the real IMU recordings in ``imu_real/`` (``../shared/data/README.md``), and of a user's own
recordings as one CSV file per sensor, converted to the model contract: 60 Hz, acc in m/s² (specific force),
gyr in rad/s, sensor frame, with the known segment.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from service.core.resample import resample_timestamps, resample_uniform
from service.core.segments import segment_index
from service.core.units import to_contract_units
from service.core.windowing import MODEL_RATE_HZ


@dataclass(frozen=True)
class RealSensor:
    sensor_id: str
    imu: np.ndarray  # (T, 6) at 60 Hz, contract units
    segment: int | None  # class index, None for sensors off the seven segments (e.g. torso)
    # R_nominal_imu where the dataset itself gives one: its rotation of this sensor's frame onto a nominal segment
    # frame (x forward, y left, z up) fixed by how the sensor was mounted, not measured on the body.
    nominal_frame: np.ndarray | None = None


@dataclass(frozen=True)
class RealRecording:
    name: str  # unique, e.g. "capacitive_sub01/CSBaseline"
    source: str
    subject: str
    activity: str
    sensors: list[RealSensor] = field(default_factory=list)


XIMU3_SEGMENTS = {
    "Left Foot": "LeftFoot",
    "Left Lower Leg": "LeftLowerLeg",
    "Left Upper Leg": "LeftUpperLeg",
    "pelvis": "Pelvis",
    "Right Upper Leg": "RightUpperLeg",
    "Right Lower Leg": "RightLowerLeg",
    "Right Foot": "RightFoot",
}
CAPACITIVE_SENSORS = ("torso", "pelvis", "tibia_r", "femur_r", "tibia_l", "femur_l", "toes_r", "toes_l")
CAPACITIVE_SEGMENTS = {
    "pelvis": "Pelvis",
    "tibia_r": "RightLowerLeg",
    "femur_r": "RightUpperLeg",
    "tibia_l": "LeftLowerLeg",
    "femur_l": "LeftUpperLeg",
    "toes_r": "RightFoot",
    "toes_l": "LeftFoot",
}
CAPACITIVE_TRIALS = ("CSBaseline", "CSStiffKnee", "EMGBaseline", "EMGStiffKnee")
GAITMAP_FILES = {  # file: (rate Hz, subject, activity)
    "imu_sample_not_rotated.csv": (204.8, "spc2019_5047", "walk"),
    "imu_sample_healthy_stair_up.csv": (204.8, "madstair_11", "stairs_up"),
    "imu_sample_healthy_stair_down.csv": (204.8, "madstair_11", "stairs_down"),
    # 4 x 10 m gait test, sensor frames as recorded (both feet stand tilted ~40° about y); the data README gives
    # no subject, so it is its own group.
    "imu_sample_ic_stride.csv": (102.4, "gaitmap_ic_stride_unknown", "walk"),
}
# gaitmap also ships the not-rotated recording with its axes turned onto gaitmap's foot sensor frame (x toward the
# toe, y left, z up, by the sensor's mounting): it is read for that rotation only (the same motion twice would count
# twice), which becomes the sensors' ``nominal_frame``.
GAITMAP_ROTATED = {"imu_sample_not_rotated.csv": "imu_sample.csv"}
# Not read: imu_sample_ms_left/right.csv, whose accelerometer norm has a median of
# about 19 m/s² over a long walk (2 g, against 9.7–11.5 in every other recording): their units are not the
# documented ones.


def read_ximu3(data_dir: Path) -> RealRecording:
    """Seven x-IMU3 devices (about 50 Hz, irregular), resampled by timestamp onto one 60 Hz grid."""
    root = data_dir / "imu_real" / "ximu3_lowerbody"
    streams = {}
    for folder in sorted(p for p in root.iterdir() if p.is_dir()):
        label = folder.name.rsplit(" ", 2)[0]
        table = np.loadtxt(folder / "Inertial.csv", delimiter=",", skiprows=1)
        t_s = table[:, 0] * 1e-6
        imu = to_contract_units(table[:, [4, 5, 6, 1, 2, 3]], "g", "deg/s")
        streams[XIMU3_SEGMENTS[label]] = (t_s, imu, folder.name)
    t0 = max(s[0][0] for s in streams.values())
    t1 = min(s[0][-1] for s in streams.values())
    sensors = []
    for seg, (t_s, imu, name) in streams.items():
        keep = (t_s >= t0 - 0.05) & (t_s <= t1 + 0.05)
        grid, resampled = resample_timestamps(t_s[keep], imu[keep], MODEL_RATE_HZ)
        n = int(np.floor((t1 - t0) * MODEL_RATE_HZ))
        start = int(np.searchsorted(grid, t0))
        sensors.append(RealSensor(name, resampled[start : start + n], segment_index(seg)))
    return RealRecording("ximu3_lowerbody", "ximu3_lowerbody", "ximu3_unknown", "mixed_lower_body", sensors)


def _read_trc(path: Path) -> np.ndarray:
    """Numeric rows of an OpenSim TRC file: ``(T, 2 + 3 * n_markers)`` (frame, time, xyz...)."""
    rows = [line.split() for line in path.read_text().splitlines()[5:] if line.strip()]
    return np.array(rows, dtype=np.float64)


def read_capacitive(data_dir: Path, trial: str) -> RealRecording:
    """Eight Xsens IMUs at 100 Hz (m/s², rad/s), treadmill walking of Sub01."""
    folder = data_dir / "imu_real" / "capacitive_sub01" / trial
    acc = _read_trc(folder / f"OpenSim_Sub01_{trial}_Accel.trc")[:, 2:]
    gyr = _read_trc(folder / f"OpenSim_Sub01_{trial}_Gyro.trc")[:, 2:]
    n = min(len(acc), len(gyr))
    sensors = []
    for k, name in enumerate(CAPACITIVE_SENSORS):
        imu = np.concatenate([acc[:n, 3 * k : 3 * k + 3], gyr[:n, 3 * k : 3 * k + 3]], axis=1)
        seg = CAPACITIVE_SEGMENTS.get(name)
        sensors.append(
            RealSensor(f"{name}_imu", resample_uniform(imu, 100.0, MODEL_RATE_HZ), segment_index(seg) if seg else None)
        )
    activity = "walk_stiffknee" if "StiffKnee" in trial else "walk"
    return RealRecording(f"capacitive_sub01/{trial}", "capacitive_sub01", "capacitive_Sub01", activity, sensors)


def read_gaitmap(data_dir: Path, file: str) -> RealRecording:
    """Left and right foot IMUs (m/s², deg/s, raw sensor frame) of the gaitmap example data."""
    rate, subject, activity = GAITMAP_FILES[file]
    folder = data_dir / "imu_real" / "gaitmap_foot"
    raw = _gaitmap_feet(folder / file)
    rotated = _gaitmap_feet(folder / GAITMAP_ROTATED[file]) if file in GAITMAP_ROTATED else None
    sensors = []
    for side, seg in (("left_sensor", "LeftFoot"), ("right_sensor", "RightFoot")):
        nominal = None if rotated is None else rotation_between(raw[side], rotated[side], GAITMAP_ROTATED[file])
        sensors.append(RealSensor(side, _gaitmap_convert(raw[side], rate), segment_index(seg), nominal))
    return RealRecording(f"gaitmap_foot/{file.removesuffix('.csv')}", "gaitmap_foot", subject, activity, sensors)


def _gaitmap_feet(path: Path) -> dict[str, np.ndarray]:
    """``left_sensor`` / ``right_sensor`` → ``(T, 6)`` acc, gyr as stored (two header rows: sensor, axis)."""
    with open(path) as fh:
        sensor_row, axis_row = fh.readline().strip().split(","), fh.readline().strip().split(",")
    table = np.loadtxt(path, delimiter=",", skiprows=2)
    columns = ["acc_x", "acc_y", "acc_z", "gyr_x", "gyr_y", "gyr_z"]
    where = {(s_, a): i for i, (s_, a) in enumerate(zip(sensor_row, axis_row, strict=True))}
    return {side: table[:, [where[side, c] for c in columns]] for side in ("left_sensor", "right_sensor")}


def rotation_between(raw: np.ndarray, turned: np.ndarray, what: str, tol: float = 1e-6) -> np.ndarray:
    """The proper rotation R with ``turned ≈ raw @ R.T`` for the acc and gyr rows of ``(T, 6)`` arrays (Kabsch);
    ``ValueError`` naming ``what`` unless it reproduces ``turned`` to ``tol`` (relative to the largest value)."""
    if raw.shape != turned.shape:
        raise ValueError(f"{what} has {len(turned)} rows of {turned.shape[1]}, the raw recording {raw.shape}")
    a = np.concatenate([raw[:, :3], raw[:, 3:]])
    b = np.concatenate([turned[:, :3], turned[:, 3:]])
    u, _, vt = np.linalg.svd(a.T @ b)
    R = vt.T @ np.diag([1.0, 1.0, np.sign(np.linalg.det(vt.T @ u.T))]) @ u.T  # proper: no reflection
    residual = np.abs(b - a @ R.T).max() / np.abs(b).max()
    if residual > tol:
        raise ValueError(f"{what} is not a rotation of the raw recording (relative residual {residual:.2g})")
    return R


def _gaitmap_convert(raw: np.ndarray, rate_hz: float) -> np.ndarray:
    return resample_uniform(to_contract_units(raw, "m/s^2", "deg/s"), rate_hz, MODEL_RATE_HZ)


def read_recording(data_dir: Path, name: str) -> RealRecording:
    """One recording by its name (``ximu3_lowerbody``, ``capacitive_sub01/<trial>``, ``gaitmap_foot/<file>``),
    reading only its own files."""
    if name not in RECORDING_NAMES:
        raise KeyError(f"no recording {name!r}; known: {RECORDING_NAMES}")
    source, _, part = name.partition("/")
    if source == "ximu3_lowerbody":
        return read_ximu3(data_dir)
    if source == "capacitive_sub01":
        return read_capacitive(data_dir, part)
    return read_gaitmap(data_dir, f"{part}.csv")


RECORDING_NAMES = (
    ["ximu3_lowerbody"]
    + [f"capacitive_sub01/{t}" for t in CAPACITIVE_TRIALS]
    + [f"gaitmap_foot/{f.removesuffix('.csv')}" for f in GAITMAP_FILES]
)


def read_all_real(data_dir: Path) -> list[RealRecording]:
    """Every real recording with known placement."""
    recs = [read_ximu3(data_dir)] + [read_capacitive(data_dir, t) for t in CAPACITIVE_TRIALS]
    return recs + [read_gaitmap(data_dir, f) for f in GAITMAP_FILES]


def read_csv_imu(path: Path, skip_columns: int = 0) -> np.ndarray:
    """One sensor's CSV file: a header row, then rows whose columns ``skip_columns`` … ``skip_columns + 5`` are
    acc x, y, z and gyr x, y, z in the file's units (leading columns such as time are skipped)."""
    try:
        data = np.loadtxt(path, delimiter=",", skiprows=1, ndmin=2)
    except ValueError as exc:
        raise ValueError(f"{path}: expected a header row, then rows of comma-separated numbers ({exc})") from None
    if data.shape[1] < skip_columns + 6:
        raise ValueError(
            f"{path}: expected {skip_columns} column(s) to skip then 6 (acc x y z, gyr x y z), "
            f"got {data.shape[1]} column(s)"
        )
    if not np.isfinite(data[:, skip_columns : skip_columns + 6]).all():
        raise ValueError(f"{path}: the six IMU columns must be finite numbers, found NaN or Inf")
    return data[:, skip_columns : skip_columns + 6]


def csv_recording(
    name: str,
    files: list[tuple[str, Path]],
    rate_hz: float,
    acc_unit: str = "m/s^2",
    gyr_unit: str = "rad/s",
    skip_columns: int = 0,
) -> RealRecording:
    """A labelled recording of one's own, from ``(segment name, CSV path)`` pairs sampled at ``rate_hz`` in the
    given units (``read_csv_imu``), converted to the contract like the recordings above."""
    sensors = []
    for segment, path in files:
        raw = to_contract_units(read_csv_imu(path, skip_columns), acc_unit, gyr_unit)
        imu = resample_uniform(raw, rate_hz, MODEL_RATE_HZ)  # unchanged at the model rate
        sensors.append(RealSensor(f"{segment}:{path.name}", imu, segment_index(segment)))
    return RealRecording(name, "csv", "unknown", "unknown", sensors)
