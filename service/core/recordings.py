"""Readers of the real IMU recordings in ``imu_real/`` (``../shared/data/README.md``), and of a user's own
recordings as one CSV file per sensor, converted to the model contract: 60 Hz, acc in m/s² (specific force),
gyr in rad/s, sensor frame, with the known segment.
"""

from __future__ import annotations

import csv
import gzip
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from service.core.flex import ReadoutCheck
from service.core.opensim import read_opensim_storage, storage_cells
from service.core.resample import resample_timestamps, resample_uniform
from service.core.rotations import matrix_from_quat, repair_quaternions
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
GAITMAP_SKIPPED = frozenset({"imu_sample_ms_left.csv", "imu_sample_ms_right.csv", *GAITMAP_ROTATED.values()})


def _files(folder: Path, pattern: str) -> list[Path]:
    """The files in ``folder`` matching ``pattern``, plain or gzipped (``pattern`` + ``.gz``): the data directory may
    hold either form of any file; where it holds both, the plain one."""
    plain = sorted(folder.glob(pattern))
    names = {p.name for p in plain}
    return plain + [p for p in sorted(folder.glob(f"{pattern}.gz")) if p.name.removesuffix(".gz") not in names]


def _one_file(folder: Path, pattern: str) -> Path:
    """The one file in ``folder`` matching ``pattern``, plain or gzipped; else an error naming what was found."""
    found = _files(folder, pattern)
    if len(found) != 1:
        names = [p.name for p in found] or "none"
        raise FileNotFoundError(f"{folder}: expected one file {pattern} (or {pattern}.gz), found {names}")
    return found[0]


def _open_text(path: Path):
    """A text file, plain or gzipped (by its ``.gz`` suffix)."""
    return gzip.open(path, "rt", newline="") if path.suffix == ".gz" else open(path, newline="")


def _plain_name(path: Path) -> str:
    return path.name.removesuffix(".gz")


def read_ximu3(data_dir: Path, name: str = "ximu3_lowerbody") -> RealRecording:
    """x-IMU3 devices (about 50 Hz, irregular), one folder each (``<label> <serial> (UDP)``, the label naming the
    segment, ``XIMU3_SEGMENTS``; other labels are read with no segment), resampled by timestamp onto one 60 Hz grid
    over the time all devices recorded."""
    root = data_dir / "imu_real" / name
    streams = []
    for folder in sorted(p for p in root.iterdir() if p.is_dir() and _files(p, "Inertial.csv")):
        label = folder.name.rsplit(" ", 2)[0]
        table = np.loadtxt(_one_file(folder, "Inertial.csv"), delimiter=",", skiprows=1)
        t_s = table[:, 0] * 1e-6
        imu = to_contract_units(table[:, [4, 5, 6, 1, 2, 3]], "g", "deg/s")
        seg = XIMU3_SEGMENTS.get(label)
        streams.append((t_s, imu, folder.name, segment_index(seg) if seg else None))
    t0 = max(s[0][0] for s in streams)
    t1 = min(s[0][-1] for s in streams)
    sensors = []
    for t_s, imu, folder_name, seg in streams:
        keep = (t_s >= t0 - 0.05) & (t_s <= t1 + 0.05)
        grid, resampled = resample_timestamps(t_s[keep], imu[keep], MODEL_RATE_HZ)
        n = int(np.floor((t1 - t0) * MODEL_RATE_HZ))
        start = int(np.searchsorted(grid, t0))
        sensors.append(RealSensor(folder_name, resampled[start : start + n], seg))
    subject = "ximu3_unknown" if name == "ximu3_lowerbody" else f"{name}_unknown"  # no subject ids are given
    return RealRecording(name, name, subject, "mixed_lower_body", sensors)


def _read_trc(path: Path) -> tuple[np.ndarray, list[str], float]:
    """An OpenSim TRC file: numeric rows ``(T, 2 + 3 * n_markers)`` (frame, time, xyz...), the marker names and
    the data rate (Hz) its header gives."""
    with _open_text(path) as fh:
        lines = fh.read().splitlines()
    rate = float(dict(zip(lines[1].split("\t"), lines[2].split("\t"), strict=False))["DataRate"])
    rows = [line.split() for line in lines[5:] if line.strip()]
    return np.array(rows, dtype=np.float64), lines[3].split("\t")[2:], rate


def read_capacitive(data_dir: Path, trial: str, source: str = "capacitive_sub01") -> RealRecording:
    """Xsens IMUs of the capacitive-sensing study (m/s², rad/s; Sub01: eight at 100 Hz), treadmill walking: the
    ``OpenSim_<subject>_<trial>_Accel.trc`` / ``_Gyro.trc`` pair of one trial folder. Sensors are named by the
    files' header (``CAPACITIVE_SEGMENTS``; others, such as the torso, are read with no segment)."""
    folder = data_dir / "imu_real" / source / trial
    accel = _one_file(folder, f"OpenSim_*_{trial}_Accel.trc")
    subject = _plain_name(accel).removeprefix("OpenSim_").removesuffix(f"_{trial}_Accel.trc")
    acc, names, rate = _read_trc(accel)
    gyr, gyr_names, gyr_rate = _read_trc(_one_file(folder, f"OpenSim_{subject}_{trial}_Gyro.trc"))
    if gyr_names != names or gyr_rate != rate:
        raise ValueError(f"{folder}: Accel and Gyro files disagree on sensors or rate ({names}, {gyr_names})")
    n = min(len(acc), len(gyr))
    sensors = []
    for k, column in enumerate(names):
        name = column.removesuffix("_offset_imu").removesuffix("_imu")
        imu = np.concatenate([acc[:n, 2 + 3 * k : 5 + 3 * k], gyr[:n, 2 + 3 * k : 5 + 3 * k]], axis=1)
        seg = CAPACITIVE_SEGMENTS.get(name)
        sensors.append(
            RealSensor(f"{name}_imu", resample_uniform(imu, rate, MODEL_RATE_HZ), segment_index(seg) if seg else None)
        )
    activity = "walk_stiffknee" if "StiffKnee" in trial else "walk"
    return RealRecording(f"{source}/{trial}", source, f"capacitive_{subject}", activity, sensors)


def read_gaitmap(data_dir: Path, file: str) -> RealRecording:
    """Left and right foot IMUs (m/s², deg/s, raw sensor frame) of the gaitmap example data; the rate, subject and
    activity of a file not in ``GAITMAP_FILES`` come from the data directory's ``index.csv``."""
    rate, subject, activity = GAITMAP_FILES.get(file) or _indexed(data_dir, f"imu_real/gaitmap_foot/{file}")
    folder = data_dir / "imu_real" / "gaitmap_foot"
    raw = _gaitmap_feet(_one_file(folder, file))
    rotated = _gaitmap_feet(_one_file(folder, GAITMAP_ROTATED[file])) if file in GAITMAP_ROTATED else None
    sensors = []
    for side, seg in (("left_sensor", "LeftFoot"), ("right_sensor", "RightFoot")):
        nominal = None if rotated is None else rotation_between(raw[side], rotated[side], GAITMAP_ROTATED[file])
        sensors.append(RealSensor(side, _gaitmap_convert(raw[side], rate), segment_index(seg), nominal))
    return RealRecording(f"gaitmap_foot/{file.removesuffix('.csv')}", "gaitmap_foot", subject, activity, sensors)


def _gaitmap_feet(path: Path) -> dict[str, np.ndarray]:
    """``left_sensor`` / ``right_sensor`` → ``(T, 6)`` acc, gyr as stored (two header rows: sensor, axis)."""
    with _open_text(path) as fh:
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


def _indexed(data_dir: Path, path: str) -> tuple[float, str, str]:
    """(rate Hz, subject, activity) of a data file from ``index.csv`` (a blank subject: the file is its own)."""
    with open(data_dir / "index.csv", newline="") as fh:
        row = next((r for r in csv.DictReader(fh) if r["path"] in (path, f"{path}.gz")), None)
    if row is None or not row["fps"]:
        raise ValueError(f"{path}: index.csv gives no sample rate for it")
    return float(row["fps"]), row["subject"] or f"{Path(path).stem}_unknown", row["activity"] or "unknown"


def _is_gaitmap_imu(path: Path) -> bool:
    with _open_text(path) as fh:
        return "left_sensor" in fh.readline() and "acc_x" in fh.readline()


def recording_names(data_dir: Path) -> list[str]:
    """The recordings under ``imu_real/`` that these readers read, found by their files' layout rather than from a
    fixed list, so that a recording added beside the published ones (another capacitive subject or trial, another
    x-IMU3 session, another gaitmap-format walk listed in ``index.csv``) is read and scored like them:

    - ``capacitive_*/<trial>/OpenSim_<subject>_<trial>_Accel.trc`` (with its ``_Gyro.trc``): ``capacitive_*/<trial>``
    - ``ximu3_*/`` holding device folders with ``Inertial.csv``: ``ximu3_*``
    - ``gaitmap_foot/<file>.csv`` in gaitmap's two-header-row IMU layout, but for ``GAITMAP_SKIPPED``:
      ``gaitmap_foot/<file>`` (the published four first, in ``GAITMAP_FILES`` order)
    - ``movingreality/<participant>/<trial>/`` holding the five sensors' ``<segment>.csv.gz`` (or ``.csv``):
      ``movingreality/<participant>/<trial>``
    """
    root = data_dir / "imu_real"
    names = [p.name for p in sorted(root.glob("ximu3_*")) if _files(p, "*/Inertial.csv")]
    for source in sorted(root.glob("capacitive_*")):
        trials = (t for t in sorted(source.iterdir()) if t.is_dir() and _files(t, f"OpenSim_*_{t.name}_Accel.trc"))
        names += [f"{source.name}/{t.name}" for t in trials]
    gaitmap = root / "gaitmap_foot"
    present = {_plain_name(p): p for p in (_files(gaitmap, "*.csv") if gaitmap.is_dir() else [])}
    files = [f for f in GAITMAP_FILES if f in present]
    extra = sorted(f for f in present if f not in GAITMAP_FILES and f not in GAITMAP_SKIPPED)
    files += [f for f in extra if _is_gaitmap_imu(present[f])]
    names += [f"gaitmap_foot/{f.removesuffix('.csv')}" for f in files]
    movingreality = root / "movingreality"
    trials = sorted(movingreality.glob("*/*")) if movingreality.is_dir() else []
    return names + [f"movingreality/{t.parent.name}/{t.name}" for t in trials if _is_movingreality_trial(t)]


def read_recording(data_dir: Path, name: str) -> RealRecording:
    """One recording by its name (``recording_names``: ``ximu3_lowerbody``, ``capacitive_sub01/<trial>``,
    ``gaitmap_foot/<file>``), reading only its own files."""
    known = recording_names(data_dir)
    if name not in known:
        raise KeyError(f"no recording {name!r}; known: {known}")
    return _read(data_dir, name)


def _read(data_dir: Path, name: str) -> RealRecording:
    """The reader of a name ``recording_names`` gave, by its source folder."""
    source, _, part = name.partition("/")
    if source.startswith("ximu3_"):
        return read_ximu3(data_dir, source)
    if source.startswith("capacitive_"):
        return read_capacitive(data_dir, part, source)
    if source == "movingreality":
        participant, trial = part.split("/")
        return read_movingreality(data_dir, participant, trial)
    return read_gaitmap(data_dir, f"{part}.csv")


# The recordings of the published data directory (../shared/data/README.md); ``recording_names`` finds more.
RECORDING_NAMES = (
    ["ximu3_lowerbody"]
    + [f"capacitive_sub01/{t}" for t in CAPACITIVE_TRIALS]
    + [f"gaitmap_foot/{f.removesuffix('.csv')}" for f in GAITMAP_FILES]
    + [f"movingreality/pp0{n}/{trial}" for n in range(1, 9) for trial in ("1Reg", "FBPO" if n == 6 else "2Reg")]
)


def read_all_real(data_dir: Path) -> list[RealRecording]:
    """Every real recording with known placement that the data directory holds (``recording_names``)."""
    return [_read(data_dir, name) for name in recording_names(data_dir)]


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


@dataclass(frozen=True)
class OrientedSensor:
    """A real sensor with its own orientation output: acc (T, 3) m/s², gyr (T, 3) rad/s, q_world_sensor (T, 4)
    w x y z in its world frame (z up), at ``rate_hz``; ``repaired_rows``: how many of the file's orientation rows
    were not unit quaternions and were taken from their neighbours (``service.core.rotations.repair_quaternions``;
    the capacitive study's files, whose rows come out unit; MovingReality's are unit within 1e-6 as written)."""

    name: str
    acc: np.ndarray
    gyr: np.ndarray
    q_world_sensor: np.ndarray
    rate_hz: float
    repaired_rows: int = 0


MOVINGREALITY_SEGMENTS = {
    "lumbar": "Pelvis",
    "leftshank": "LeftLowerLeg",
    "rightshank": "RightLowerLeg",
    "leftfoot": "LeftFoot",
    "rightfoot": "RightFoot",
}


def _is_movingreality_trial(folder: Path) -> bool:
    return folder.is_dir() and all(_files(folder, f"{name}.csv") for name in MOVINGREALITY_SEGMENTS)


def read_movingreality(data_dir: Path, participant: str, trial: str) -> RealRecording:
    """One MovingReality treadmill trial as a labelled recording: the five Xsens MTw (m/s², rad/s, 100 Hz; lumbar
    → Pelvis, shanks, feet: ``MOVINGREALITY_SEGMENTS``) resampled to 60 Hz over the rows all five recorded (the
    files of a trial share one packet counter; a few end a row early)."""
    sensors = read_movingreality_trial(data_dir, participant, trial)
    n = min(len(s.acc) for s in sensors)
    return RealRecording(
        f"movingreality/{participant}/{trial}",
        "movingreality",
        f"movingreality_{participant}",
        "walk",
        [
            RealSensor(
                s.name,
                resample_uniform(np.concatenate([s.acc[:n], s.gyr[:n]], axis=1), s.rate_hz, MODEL_RATE_HZ),
                segment_index(MOVINGREALITY_SEGMENTS[s.name]),
            )
            for s in sensors
        ],
    )


def read_movingreality_trial(data_dir: Path, participant: str, trial: str) -> list[OrientedSensor]:
    """One MovingReality treadmill trial (``imu_real/movingreality/<pp>/<trial>``): five Xsens MTw with their
    orientation to ENU, 100 Hz (``../shared/data/README.md``). Sensors in ``MOVINGREALITY_SEGMENTS`` order."""
    folder = data_dir / "imu_real" / "movingreality" / participant / trial
    sensors = []
    for name in MOVINGREALITY_SEGMENTS:
        table = np.loadtxt(_one_file(folder, f"{name}.csv"), delimiter=",", skiprows=1)
        rate = 1.0 / float(np.median(np.diff(table[:, 0])))
        sensors.append(OrientedSensor(name, table[:, 1:4], table[:, 4:7], table[:, 7:11], rate))
    return sensors


def read_capacitive_oriented(data_dir: Path, trial: str, source: str = "capacitive_sub01") -> dict[str, OrientedSensor]:
    """A capacitive-study trial's IMUs with their orientations (``OpenSim_*_Orientations.sto``: quaternions w, x,
    y, z of each sensor frame in a z-up world, checked: the rotated specific force averages +9.7-9.96 m/s² up),
    keyed by segment (``CAPACITIVE_SEGMENTS``), at 100 Hz. Sub01's left femur sensor has rows that are not unit
    quaternions in every trial (5-12 % beyond 1 ± 0.1: the export interpolated across sign flips); they are
    repaired from their neighbours (``repair_quaternions``; ``repaired_rows`` says how many), which takes spikes of
    up to 40° out of the left knee's flexion."""
    folder = data_dir / "imu_real" / source / trial
    orient = _one_file(folder, f"OpenSim_*_{trial}_Orientations.sto")
    with _open_text(orient) as fh:
        _, names, rows = storage_cells(fh.read(), str(orient))
    names = names[1:]
    q = np.array([[[float(v) for v in cell.split(",")] for cell in row[1:]] for row in rows])
    stem = _plain_name(orient).removesuffix("_Orientations.sto")
    acc, acc_names, rate = _read_trc(_one_file(folder, f"{stem}_Accel.trc"))
    gyr, _, _ = _read_trc(_one_file(folder, f"{stem}_Gyro.trc"))
    n = min(len(q), len(acc), len(gyr))
    out = {}
    for k, column in enumerate(names):
        seg = CAPACITIVE_SEGMENTS.get(column.removesuffix("_offset_imu").removesuffix("_imu"))
        if seg is None:
            continue
        j = acc_names.index(column)
        try:
            q_unit, repaired = repair_quaternions(q[:n, k])
        except ValueError as exc:
            raise ValueError(f"{orient}: column {column}: {exc}") from exc
        out[seg] = OrientedSensor(
            column, acc[:n, 2 + 3 * j : 5 + 3 * j], gyr[:n, 2 + 3 * j : 5 + 3 * j], q_unit, rate, int(repaired.sum())
        )
    return out


# The capacitive sleeves' channels (Pearl et al. 2022, shank and thigh study), distal to proximal: four on the
# shank, three on the thigh; the left and right files list them in different orders, so they are read by name.
CAPACITIVE_CHANNELS: tuple[str, ...] = (
    "Bot_Shank",
    "2nd_Bot_Shank",
    "2nd_Top_Shank",
    "Top_Shank",
    "Bot_Thigh",
    "Med_Thigh",
    "Top_Thigh",
)
CAPACITIVE_FAILURE = 0.5  # a read-out failure: a channel off its median of the first 10 s by over half of it
CAPACITIVE_REFERENCE_S = 10.0


def _read_sleeve_file(data_dir: Path, trial: str, side: str, source: str) -> tuple[list[str], np.ndarray]:
    """One leg's sleeve file (``*_LCS.mot`` / ``*_RCS.mot``): its column names and numeric rows."""
    folder = data_dir / "imu_real" / source / trial
    path = _one_file(folder, f"OpenSim_*_{trial}_{side[0]}CS.mot")
    with _open_text(path) as fh:
        _, names, rows = read_opensim_storage(fh.read(), str(path))
    return names, rows


def read_capacitive_sleeve(
    data_dir: Path, trial: str, side: str, source: str = "capacitive_sub01", until_failure: bool = True
) -> tuple[np.ndarray, float]:
    """One leg's sleeve (``side`` "Left" or "Right": ``*_LCS.mot`` / ``*_RCS.mot``) → ``(T, 7)`` raw capacitance
    readings in ``CAPACITIVE_CHANNELS`` order and the rate (Hz, from the time column). The recording stops at its
    first read-out failure (a channel not finite, or off its median over the first 10 s by more than
    ``CAPACITIVE_FAILURE`` of it): Sub01's right sleeve fails from 39.7 s of the baseline trial on (readings
    climbing to 1e6-1e8) and never recovers. ``until_failure=False`` keeps every row, failed or not. The rows are
    as the file gives them, not synchronised with the Xsens sensors (``capacitive_sleeve_sync``)."""
    names, x = _read_sleeve_file(data_dir, trial, side, source)
    missing = [c for c in CAPACITIVE_CHANNELS if c not in names]
    if missing:
        raise ValueError(f"{source}/{trial} {side} sleeve: no column {missing}; the file has {names}")
    cols = [names.index(c) for c in CAPACITIVE_CHANNELS]
    cs = x[:, cols]
    rate = 1.0 / float(np.median(np.diff(x[:, 0])))
    check = ReadoutCheck(rate, CAPACITIVE_REFERENCE_S, CAPACITIVE_FAILURE)
    check.first_failure(cs[: check.reference_rows])  # the reference: the median of the first 10 s
    failure = check.first_failure(cs) if until_failure else None
    if failure is not None:
        cs = cs[: failure.row]
    return cs, rate


# Synchronising a sleeve with the Xsens sensors. The sleeve's read-out board carries its own IMU (the file's
# ``BNOx``, ``BNOy``, ``BNOZ`` columns: Euler angles in degrees of an unstated convention) and sits on the shank.
# Over a stride one of its angles follows how one of the Xsens shank sensor's axes tilts against the vertical (Sub01:
# correlation 0.96-0.99 at the best lag, 0.91-0.94 for a second pair). The lag that matches them best is the
# sleeve's delay: Sub01's baseline trial reads its left sleeve 0.25 s and its right sleeve 0.39 s behind the
# Xsens rows, the same in both halves of the trial; the stiff-knee trial's sleeves are in step (0.00 / -0.01 s).
SLEEVE_BOARD_COLUMNS = ("BNOx", "BNOy", "BNOZ")
SYNC_MAX_S = 2.0  # lags searched either way (a stride is about 1.1 s: the true lag must be well within one)
SYNC_HIGH_PASS_S = 1.1  # about a stride: what is left is each angle's swing within the stride
SYNC_MIN_CORRELATION = 0.9  # weaker than this, the board and the shank do not match: no lag is applied


@dataclass(frozen=True)
class SleeveSync:
    lag_rows: int  # the sleeve's row t + lag_rows was read at the Xsens row t (positive: the sleeve is behind)
    rate_hz: float
    correlation: float  # |correlation| of the best-matching board angle and shank axis at that lag
    board_angle: str  # the board column that matched
    shank_axis: int  # the Xsens shank sensor's axis (0 x, 1 y, 2 z) whose vertical component matched

    @property
    def lag_s(self) -> float:
        return self.lag_rows / self.rate_hz

    @property
    def applied_rows(self) -> int:
        """The lag to apply: 0 where the match is too weak to trust."""
        return self.lag_rows if self.correlation >= SYNC_MIN_CORRELATION else 0


def _high_pass(x: np.ndarray, rows: int) -> np.ndarray:
    """``x`` minus its centred moving mean over ``rows`` (edges: the mean of what the window holds)."""
    c = np.concatenate([np.zeros((1, *x.shape[1:])), np.cumsum(x, axis=0)])
    k = np.arange(len(x))
    lo, hi = np.clip(k - rows // 2, 0, len(x)), np.clip(k + rows - rows // 2, 0, len(x))
    return x - (c[hi] - c[lo]) / (hi - lo).reshape(-1, *[1] * (x.ndim - 1))


def _lagged_correlation(reference: np.ndarray, signal: np.ndarray, lags: np.ndarray) -> np.ndarray:
    """Correlation of ``reference[t]`` with ``signal[t + lag]`` for each lag (overlapping rows only)."""
    n = min(len(reference), len(signal))
    out = np.empty(len(lags))
    for k, lag in enumerate(lags):
        a = reference[max(0, -lag) : n - max(0, lag)]
        b = signal[max(0, lag) : n + min(0, lag)]
        a, b = a - a.mean(), b - b.mean()
        out[k] = float(a @ b / np.sqrt((a @ a) * (b @ b) + 1e-30))
    return out


def capacitive_sleeve_sync(
    data_dir: Path, trial: str, side: str, source: str = "capacitive_sub01", rows: int | None = None
) -> SleeveSync:
    """How far one leg's sleeve rows lag the trial's Xsens rows, from the sleeve board's own IMU against the Xsens
    shank sensor (see ``SLEEVE_BOARD_COLUMNS``). ``rows``: only the first rows count (a sleeve that fails later:
    ``read_capacitive_sleeve``'s length)."""
    names, x = _read_sleeve_file(data_dir, trial, side, source)
    rate = 1.0 / float(np.median(np.diff(x[:, 0])))
    if not set(SLEEVE_BOARD_COLUMNS) <= set(names):  # a read-out without the board's IMU: nothing to match
        return SleeveSync(0, rate, 0.0, "", 0)
    shank = read_capacitive_oriented(data_dir, trial, source)[f"{side}LowerLeg"]
    if abs(shank.rate_hz - rate) > 0.01 * rate:
        raise ValueError(f"{trial} {side}: sleeve at {rate:.1f} Hz, Xsens at {shank.rate_hz:.1f} Hz")
    n = min(len(x), len(shank.q_world_sensor), rows or len(x))
    board = _high_pass(
        np.unwrap(np.deg2rad(x[:n, [names.index(c) for c in SLEEVE_BOARD_COLUMNS]]), axis=0),
        round(SYNC_HIGH_PASS_S * rate),
    )
    # the vertical component of each shank sensor axis: row 2 of R_world_sensor
    tilt = _high_pass(matrix_from_quat(shank.q_world_sensor[:n])[:, 2, :], round(SYNC_HIGH_PASS_S * rate))
    lags = np.arange(-round(SYNC_MAX_S * rate), round(SYNC_MAX_S * rate) + 1)
    best = SleeveSync(0, rate, 0.0, "", 0)
    for j, column in enumerate(SLEEVE_BOARD_COLUMNS):
        for axis in range(3):
            c = np.abs(_lagged_correlation(tilt[:, axis], board[:, j], lags))
            k = int(c.argmax())
            if c[k] > best.correlation:
                best = SleeveSync(int(lags[k]), rate, float(c[k]), column, axis)
    return best
