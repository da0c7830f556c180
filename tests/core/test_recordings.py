"""The readers of the real recordings (service/core/recordings.py) against the data README's index: every
recording read, at the model rate for its whole length, in contract units, with the segments it is labelled with."""

from __future__ import annotations

import csv
from pathlib import Path

import numpy as np
import pytest

from service.core.recordings import RECORDING_NAMES, csv_recording, read_all_real, read_csv_imu, read_recording
from service.core.segments import SEGMENTS
from service.core.windowing import MODEL_RATE_HZ

# Sensors whose accelerometer is off in the data as published: the capacitive subject's left-foot Xsens reads
# 12.1-12.2 m/s² standing still, in all four trials (its z about 10.8 where the right foot's reads 8.2). Kept as
# recorded: a real sensor error the models meet.
GRAVITY_AS_READ = {("capacitive_sub01", "toes_l_imu"): 12.15}


@pytest.fixture(scope="module")
def recordings(data_dir: Path):
    return {r.name: r for r in read_all_real(data_dir)}


def _index_duration_s(data_dir: Path, name: str) -> float:
    """The IMU file's duration as index.csv gives it (x-IMU3: the shortest device, the readers keep the overlap)."""
    with open(data_dir / "index.csv", newline="") as fh:
        rows = list(csv.DictReader(fh))
    if name == "ximu3_lowerbody":
        return min(float(r["duration_s"]) for r in rows if r["path"].endswith("Inertial.csv"))
    if name.startswith("movingreality/"):  # five files a trial; a few end a row early, the readers keep the overlap
        return min(float(r["duration_s"]) for r in rows if r["path"].startswith(f"imu_real/{name}/"))
    source, item = name.split("/")
    suffix = f"{item}_Accel.trc" if source == "capacitive_sub01" else f"{item}.csv"
    return next(float(r["duration_s"]) for r in rows if r["source"] == source and r["path"].endswith(suffix))


def test_every_named_recording_is_read_once(recordings) -> None:
    assert sorted(recordings) == sorted(RECORDING_NAMES)
    assert "gaitmap_foot/imu_sample_ic_stride" in recordings
    assert {r.subject for r in recordings.values() if r.source == "movingreality"} == {
        f"movingreality_pp0{n}" for n in range(1, 9)
    }


@pytest.mark.parametrize("name", RECORDING_NAMES)
def test_one_recording_read_by_name_is_the_one_read_with_all(recordings, data_dir: Path, name: str) -> None:
    one = read_recording(data_dir, name)
    assert one.name == name and [s.sensor_id for s in one.sensors] == [s.sensor_id for s in recordings[name].sensors]
    for mine, theirs in zip(one.sensors, recordings[name].sensors, strict=True):
        np.testing.assert_array_equal(mine.imu, theirs.imu)
        assert mine.segment == theirs.segment


def test_an_unknown_recording_name_says_which_exist(data_dir: Path) -> None:
    with pytest.raises(KeyError, match="known:.*ximu3_lowerbody"):
        read_recording(data_dir, "capacitive_sub01/CSRunning")


@pytest.mark.parametrize("name", RECORDING_NAMES)
def test_recording_is_at_the_model_rate_for_its_whole_length(recordings, data_dir: Path, name: str) -> None:
    expected = _index_duration_s(data_dir, name)
    for sensor in recordings[name].sensors:
        assert abs(len(sensor.imu) / MODEL_RATE_HZ - expected) < 0.3, (sensor.sensor_id, len(sensor.imu), expected)


@pytest.mark.parametrize("name", RECORDING_NAMES)
def test_recording_is_in_contract_units(recordings, name: str) -> None:
    """Specific force in m/s² (a median norm near 1 g, not 1 or 2 g-units) and rates in rad/s (walking swings a
    leg at a few rad/s; deg/s would read ~57 times more; the pelvis turns slowest)."""
    fastest = 0.0
    for sensor in recordings[name].sensors:
        if sensor.segment is None:
            continue
        acc_norm = np.linalg.norm(sensor.imu[:, :3], axis=1)
        gyr_norm = np.linalg.norm(sensor.imu[:, 3:], axis=1)
        assert 9.0 < np.median(acc_norm) < 13.0, (sensor.sensor_id, np.median(acc_norm))
        assert np.percentile(gyr_norm, 95) < 12.0, (sensor.sensor_id, np.percentile(gyr_norm, 95))
        fastest = max(fastest, float(np.percentile(gyr_norm, 95)))
        # standing: not turning, and the specific force steady over half a second (a slow walker's pelvis turns
        # under 0.1 rad/s while its accelerometer swings with every step)
        half = int(MODEL_RATE_HZ // 4)
        kernel = np.ones(2 * half + 1) / (2 * half + 1)
        local_mean = np.convolve(acc_norm, kernel, mode="same")
        local_std = np.sqrt(np.maximum(np.convolve(acc_norm**2, kernel, mode="same") - local_mean**2, 0.0))
        still = (gyr_norm < 0.1) & (local_std < 0.2)
        if still.sum() > MODEL_RATE_HZ:  # a second or more of standing: gravity alone
            at_rest = GRAVITY_AS_READ.get((recordings[name].source, sensor.sensor_id), 9.81)
            assert abs(np.median(acc_norm[still]) - at_rest) < 0.7, (sensor.sensor_id, np.median(acc_norm[still]))
    assert fastest > 2.0, fastest


@pytest.mark.parametrize("name", RECORDING_NAMES)
def test_recording_carries_its_segment_labels(recordings, name: str) -> None:
    labelled = sorted(s.segment for s in recordings[name].sensors if s.segment is not None)
    if name.startswith("gaitmap_foot/"):
        assert labelled == [SEGMENTS.index("LeftFoot"), SEGMENTS.index("RightFoot")]
    elif name.startswith("movingreality/"):  # lumbar, both shanks, both feet; no thighs
        thighs = {SEGMENTS.index("LeftUpperLeg"), SEGMENTS.index("RightUpperLeg")}
        assert labelled == sorted(set(range(len(SEGMENTS))) - thighs)
    else:
        assert labelled == list(range(len(SEGMENTS)))


def test_csv_recordings_convert_units_and_rate_and_refuse_non_numbers(tmp_path: Path) -> None:
    """One's own CSV files: a time column skipped, g and deg/s converted, 120 Hz resampled to 60 Hz; NaN refused."""
    t = np.arange(1200) / 120.0
    imu = np.column_stack([np.sin(t), np.cos(t), 1.0 + 0 * t, 90 * np.sin(2 * t), 0 * t, 0 * t])  # g, deg/s
    path = tmp_path / "thigh.csv"
    np.savetxt(path, np.column_stack([t, imu]), delimiter=",", header="t,ax,ay,az,gx,gy,gz", comments="")
    rec = csv_recording("mine", [("LeftUpperLeg", path)], 120.0, "g", "deg/s", skip_columns=1)
    (sensor,) = rec.sensors
    assert sensor.segment == SEGMENTS.index("LeftUpperLeg") and sensor.imu.shape == (600, 6)
    np.testing.assert_allclose(sensor.imu[100:500, 2], 9.80665, rtol=1e-6)
    np.testing.assert_allclose(sensor.imu[100:500, 3], np.radians(90) * np.sin(2 * t[200:1000:2]), atol=1e-3)
    bad = tmp_path / "bad.csv"
    bad.write_text("ax,ay,az,gx,gy,gz\n1,2,3,nan,5,6\n")
    with pytest.raises(ValueError, match="finite"):
        read_csv_imu(bad)
    (tmp_path / "words.csv").write_text("ax,ay,az,gx,gy,gz\n1,2,three,4,5,6\n")
    with pytest.raises(ValueError, match="comma-separated numbers"):
        read_csv_imu(tmp_path / "words.csv")


def test_the_gaitmap_walk_carries_gaitmap_s_own_foot_frames(data_dir: Path) -> None:
    """gaitmap's rotated copy of its walk is an exact axis permutation of the raw one (the mounting): the reader
    recovers it per foot as a proper rotation, and refuses a copy that is not a rotation of the raw data."""
    from service.core.recordings import rotation_between

    rec = read_recording(data_dir, "gaitmap_foot/imu_sample_not_rotated")
    frames = {s.sensor_id: s.nominal_frame for s in rec.sensors}
    np.testing.assert_allclose(frames["left_sensor"], [[0, 1, 0], [0, 0, 1], [1, 0, 0]], atol=1e-9)
    np.testing.assert_allclose(frames["right_sensor"], [[0, -1, 0], [0, 0, -1], [1, 0, 0]], atol=1e-9)
    assert all(s.nominal_frame is None for s in read_recording(data_dir, "gaitmap_foot/imu_sample_ic_stride").sensors)
    raw = np.random.default_rng(0).normal(size=(50, 6))
    mirrored = raw * np.array([1, 1, -1, 1, 1, -1])  # a reflection, not a rotation
    with pytest.raises(ValueError, match="copy.csv is not a rotation of the raw recording"):
        rotation_between(raw, mirrored, "copy.csv")
    with pytest.raises(ValueError, match="copy.csv has 49 rows"):
        rotation_between(raw, raw[:49], "copy.csv")


def test_recordings_added_beside_the_published_ones_are_found_and_read(data_dir: Path, tmp_path: Path) -> None:
    """A data directory with one more capacitive subject, one more x-IMU3 session and one more gaitmap-format walk
    (files linked from the published ones, index.csv extended by the walk's row): ``recording_names`` finds them by
    their layout, and they read as the recordings they were linked from, under their own names and subjects. A
    gaitmap-format walk that index.csv gives no rate for is refused by name."""
    real, fake = data_dir / "imu_real", tmp_path / "imu_real"
    fake.mkdir()
    for item in real.iterdir():
        (fake / item.name).symlink_to(item.resolve())
    (fake / "ximu3_session2").symlink_to((real / "ximu3_lowerbody").resolve())
    trial = fake / "capacitive_sub02" / "CSBaseline"
    trial.mkdir(parents=True)
    for kind in ("Accel", "Gyro"):
        (trial / f"OpenSim_Sub02_CSBaseline_{kind}.trc").symlink_to(
            real / "capacitive_sub01" / "CSBaseline" / f"OpenSim_Sub01_CSBaseline_{kind}.trc"
        )
    (fake / "gaitmap_foot").unlink()
    (fake / "gaitmap_foot").mkdir()
    for item in (real / "gaitmap_foot").iterdir():
        (fake / "gaitmap_foot" / item.name).symlink_to(item)
    (fake / "gaitmap_foot" / "my_walk.csv").symlink_to(real / "gaitmap_foot" / "imu_sample_ic_stride.csv")
    index = (data_dir / "index.csv").read_text()
    (tmp_path / "index.csv").write_text(index + "imu_real/gaitmap_foot/my_walk.csv,gaitmap_foot,,walk,,102.4,,,,,\n")

    from service.core.recordings import recording_names

    added = ["ximu3_session2", "capacitive_sub02/CSBaseline", "gaitmap_foot/my_walk"]
    assert sorted(recording_names(tmp_path)) == sorted([*RECORDING_NAMES, *added])
    twins = ["ximu3_lowerbody", "capacitive_sub01/CSBaseline", "gaitmap_foot/imu_sample_ic_stride"]
    for name, twin in zip(added, twins, strict=True):
        new, old = read_recording(tmp_path, name), read_recording(data_dir, twin)
        assert new.name == name and [s.segment for s in new.sensors] == [s.segment for s in old.sensors]
        for a, b in zip(new.sensors, old.sensors, strict=True):
            np.testing.assert_array_equal(a.imu, b.imu)
    assert read_recording(tmp_path, "capacitive_sub02/CSBaseline").subject == "capacitive_Sub02"
    assert read_recording(tmp_path, "gaitmap_foot/my_walk").subject == "my_walk_unknown"
    (tmp_path / "index.csv").write_text(index)
    with pytest.raises(ValueError, match="my_walk.csv: index.csv gives no sample rate"):
        read_recording(tmp_path, "gaitmap_foot/my_walk")


def test_gzipped_recordings_read_as_the_plain_ones(data_dir: Path, tmp_path: Path) -> None:
    """Every file of the real recordings may be gzipped in a data directory (``.trc.gz``, ``.sto.gz``, ``.mot.gz``,
    ``Inertial.csv.gz``, gaitmap's ``.csv.gz``): they are found by the same layout and read as the plain files, the
    capacitive trial's sleeves and orientations too."""
    import gzip
    import shutil

    from service.core.recordings import (
        read_capacitive_oriented,
        read_capacitive_sleeve,
        recording_names,
    )

    real, packed = data_dir / "imu_real", tmp_path / "imu_real"

    def pack(source: Path, target: Path) -> None:
        target.mkdir(parents=True, exist_ok=True)
        for item in source.iterdir():
            if item.is_dir():
                pack(item, target / item.name)
            elif item.suffix != ".gz" and item.name.startswith(("OpenSim_", "Inertial", "imu_sample")):
                with open(item, "rb") as fh, gzip.open(target / f"{item.name}.gz", "wb") as out:
                    shutil.copyfileobj(fh, out)

    pack(real / "capacitive_sub01" / "CSStiffKnee", packed / "capacitive_sub01" / "CSStiffKnee")
    pack(real / "ximu3_lowerbody", packed / "ximu3_lowerbody")
    pack(real / "gaitmap_foot", packed / "gaitmap_foot")
    shutil.copy(data_dir / "index.csv", tmp_path / "index.csv")
    # a file in both forms is read once, in its plain form
    shutil.copy(real / "gaitmap_foot" / "imu_sample_ic_stride.csv", packed / "gaitmap_foot")
    names = ["capacitive_sub01/CSStiffKnee", "ximu3_lowerbody"] + [n for n in RECORDING_NAMES if "gaitmap" in n]
    assert sorted(recording_names(tmp_path)) == sorted(names)
    for name in names:
        new, old = read_recording(tmp_path, name), read_recording(data_dir, name)
        assert [s.segment for s in new.sensors] == [s.segment for s in old.sensors] and new.subject == old.subject
        for a, b in zip(new.sensors, old.sensors, strict=True):
            np.testing.assert_array_equal(a.imu, b.imu)
            assert (a.nominal_frame is None) == (b.nominal_frame is None)
    for side in ("Left", "Right"):
        new_cs, old_cs = (read_capacitive_sleeve(d, "CSStiffKnee", side) for d in (tmp_path, data_dir))
        np.testing.assert_array_equal(new_cs[0], old_cs[0])
    new_q, old_q = (read_capacitive_oriented(d, "CSStiffKnee") for d in (tmp_path, data_dir))
    assert new_q.keys() == old_q.keys()
    for seg in old_q:
        np.testing.assert_array_equal(new_q[seg].q_world_sensor, old_q[seg].q_world_sensor)


def test_capacitive_sleeves_are_put_in_step_with_the_xsens_sensors_by_their_board_imu(
    data_dir: Path, tmp_path: Path
) -> None:
    """Sub01's sleeves lag the Xsens rows by 0.25 s (left) and 0.39-0.40 s (right) in the baseline trial and not
    in the stiff-knee trial; a sleeve file delayed by 30 more rows reads 30 rows more, and a board that does not
    move with the shank is not trusted (no lag applied)."""
    from service.core.recordings import SYNC_MIN_CORRELATION, capacitive_sleeve_sync, read_capacitive_sleeve

    lags = {
        (trial, side): capacitive_sleeve_sync(
            data_dir, trial, side, rows=len(read_capacitive_sleeve(data_dir, trial, side)[0])
        )
        for trial in ("CSBaseline", "CSStiffKnee")
        for side in ("Left", "Right")
    }
    assert all(s.correlation > 0.95 for s in lags.values())
    assert lags["CSBaseline", "Left"].lag_rows == 25 and 38 <= lags["CSBaseline", "Right"].lag_rows <= 41
    assert abs(lags["CSStiffKnee", "Left"].lag_rows) <= 1 and abs(lags["CSStiffKnee", "Right"].lag_rows) <= 1

    real = data_dir / "imu_real" / "capacitive_sub01" / "CSStiffKnee"
    trial = tmp_path / "imu_real" / "capacitive_sub01" / "CSStiffKnee"
    trial.mkdir(parents=True)
    for kind in ("Accel.trc", "Gyro.trc", "Orientations.sto"):
        (trial / f"OpenSim_Sub01_CSStiffKnee_{kind}").symlink_to(real / f"OpenSim_Sub01_CSStiffKnee_{kind}")
    lines = (real / "OpenSim_Sub01_CSStiffKnee_LCS.mot").read_text().splitlines()
    head = next(k for k, line in enumerate(lines) if line.startswith("endheader")) + 2
    rows = [line.split("\t") for line in lines[head:] if line.strip()]
    delayed = [[rows[k][0], *rows[max(k - 30, 0)][1:]] for k in range(len(rows))]  # row t + 30 holds row t
    (trial / "OpenSim_Sub01_CSStiffKnee_LCS.mot").write_text(
        "\n".join(lines[:head] + ["\t".join(r) for r in delayed]) + "\n"
    )
    shifted = capacitive_sleeve_sync(tmp_path, "CSStiffKnee", "Left")
    assert shifted.lag_rows == lags["CSStiffKnee", "Left"].lag_rows + 30
    assert shifted.applied_rows == shifted.lag_rows and abs(shifted.lag_s - shifted.lag_rows / 100) < 1e-9

    still = [[r[0], *r[1:8], "10", "20", "30"] for r in rows]  # a board that never moves
    (trial / "OpenSim_Sub01_CSStiffKnee_LCS.mot").write_text(
        "\n".join(lines[:head] + ["\t".join(r) for r in still]) + "\n"
    )
    unmatched = capacitive_sleeve_sync(tmp_path, "CSStiffKnee", "Left")
    assert unmatched.correlation < SYNC_MIN_CORRELATION and unmatched.applied_rows == 0


def test_the_capacitive_left_femur_rows_that_are_not_unit_quaternions_are_repaired(data_dir: Path) -> None:
    """Sub01's left femur file has rows that are not unit quaternions (its export interpolated across sign flips),
    which read as spikes of up to 80° per sample² in the left knee's flexion; after the repair the knee moves as
    smoothly as the right one, whose file has none."""
    from service.core.flex import fit_hinge, hinge_angle_deg
    from service.core.recordings import read_capacitive_oriented

    sensors = read_capacitive_oriented(data_dir, "CSStiffKnee")
    repaired = {seg: s.repaired_rows / len(s.q_world_sensor) for seg, s in sensors.items()}
    assert 0.03 < repaired.pop("LeftUpperLeg") < 0.15
    assert set(repaired.values()) == {0.0}
    roughness = {}
    for side in ("Left", "Right"):
        thigh, shank = (sensors[f"{side}{s}"].q_world_sensor for s in ("UpperLeg", "LowerLeg"))
        knee = hinge_angle_deg(thigh, shank, fit_hinge(thigh, shank))
        roughness[side] = np.abs(np.diff(knee, 2)).max()
    assert roughness["Left"] < 2.0 * roughness["Right"] + 1.0, roughness
