"""The streaming client a newcomer meets: reading one's own CSV files (column layouts and device presets, on the
real x-IMU3 files and on files written here in the exact format of Movella DOT and MT Manager exports), the
one-line errors, and the committed sample streamed to a real uvicorn server with the answer checked and the live
table drawn."""

from __future__ import annotations

import importlib.util
import io
import json
import subprocess
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from rich.console import Console

from benchmarks.servers import REPO, start_service, stop
from service.client import _parser, _sensors, _stream, check_units, csv_sensor_ids, read_csv_sensor
from service.client_display import LiveView
from service.core.csv_columns import PRESETS, ColumnError, parse_columns, read_mapped_csv
from service.core.recordings import XIMU3_SEGMENTS, read_csv_imu

EXAMPLES = REPO / "examples"
SAMPLE = EXAMPLES / "ximu3_lowerbody"
XIMU3_ORDER = [4, 5, 6, 1, 2, 3]  # Inertial.csv: time, gyr x y z (deg/s), acc x y z (g)


def _ximu3_files(data_dir: Path) -> list[Path]:
    return sorted((data_dir / "imu_real" / "ximu3_lowerbody").glob("*/Inertial.csv"))


def _sample_truth(data_dir: Path) -> dict[str, str]:
    """Serial number → segment, from the data directory's device folders (``<label> <serial> (UDP)``)."""
    folders = [p.parent.name for p in _ximu3_files(data_dir)]
    return {name.rsplit(" ", 2)[1]: XIMU3_SEGMENTS[name.rsplit(" ", 2)[0]] for name in folders}


def test_ximu3_preset_reads_the_real_files(data_dir: Path) -> None:
    """Every device of the x-IMU3 recording: acc and gyr come from their named columns (gyroscope first in the
    file), in g and deg/s, at the rate of the timestamps (about 50 Hz), resampled by timestamp over the dropped
    samples (7–27 per device, ../shared/data/README.md)."""
    files = _ximu3_files(data_dir)
    assert len(files) == 7
    for path in files:
        mapped = read_mapped_csv(path, PRESETS["ximu3"])
        table = np.loadtxt(path, delimiter=",", skiprows=1)
        t_s = (table[:, 0] - table[0, 0]) * 1e-6
        assert (mapped.acc_unit, mapped.gyr_unit) == ("g", "deg/s")
        assert 49.5 < mapped.rate_hz < 50.5 and 7 <= mapped.gaps <= 27, (path, mapped.rate_hz, mapped.gaps)
        grid = np.arange(len(mapped.samples)) / mapped.rate_hz
        assert grid[-1] <= t_s[-1] < grid[-1] + 1.0 / mapped.rate_hz
        expected = np.stack([np.interp(grid, t_s, table[:, c]) for c in XIMU3_ORDER], axis=1)
        np.testing.assert_allclose(mapped.samples, expected, atol=1e-9)
        gravity_g = np.linalg.norm(mapped.samples[: int(mapped.rate_hz), :3].mean(axis=0))
        assert 0.9 < gravity_g < 1.1  # the first second is still: 1 g
    # Every device's file is an Inertial.csv: the sensors are told apart by their folders.
    assert csv_sensor_ids(files) == [p.parent.name for p in files]


def test_the_sample_is_the_real_recording_cut(data_dir: Path) -> None:
    """examples/ holds what make_sample.py writes from the data directory, byte for byte, under 300 KB."""
    spec = importlib.util.spec_from_file_location("make_sample", EXAMPLES / "make_sample.py")
    make_sample = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(make_sample)
    cut = make_sample.cut(make_sample.device_files(data_dir))
    assert sorted(cut) == sorted(_sample_truth(data_dir))
    for serial, text in cut.items():
        assert (SAMPLE / f"{serial}.csv").read_bytes() == text
    licence = data_dir / "imu_real" / "ximu3_lowerbody" / "LICENSE.md"
    assert (SAMPLE / "LICENSE.md").read_bytes() == licence.read_bytes()
    files = [p for p in EXAMPLES.rglob("*") if p.is_file() and "__pycache__" not in p.parts]
    assert sum(p.stat().st_size for p in files) < 300_000
    for serial in cut:
        sensor = read_csv_sensor(SAMPLE / f"{serial}.csv", serial, PRESETS["ximu3"])
        assert 9.9 < len(sensor.samples) / sensor.sample_rate_hz <= 10.0
        assert check_units(sensor) == []
    # Read without the preset's units, gravity reads about 1 m/s²: the client warns before streaming.
    assert any("are the values in 'g'?" in w for w in check_units(replace(sensor, acc_unit="m/s^2")))


def _write(path: Path, text: str) -> Path:
    path.write_text(text)
    return path


def test_columns_by_position_and_by_header_name(tmp_path: Path) -> None:
    """A file of one's own in another order (time in ms, gyr before acc, a column to ignore): labels by position
    and header names read the same readings; the time column gives the rate."""
    rows = np.array([[10 * k, 0.1 * k, 0.2, 0.3, k, 0.0, 9.8, 7.0] for k in range(50)])
    header = "t_ms,gx,gy,gz,ax,ay,az,temp"
    path = tmp_path / "mine.csv"
    np.savetxt(path, rows, delimiter=",", header=header, comments="")
    by_position = read_mapped_csv(path, parse_columns("time_ms,gyr_x,gyr_y,gyr_z,acc_x,acc_y,acc_z,-"))
    by_name = read_mapped_csv(path, parse_columns("ax,ay,az,gx,gy,gz"))
    np.testing.assert_array_equal(by_position.samples, rows[:, [4, 5, 6, 1, 2, 3]])
    np.testing.assert_array_equal(by_name.samples, rows[:, [4, 5, 6, 1, 2, 3]])
    assert by_position.rate_hz == pytest.approx(100.0) and by_name.rate_hz is None
    # --skip-columns counts before the labels; a sensor without a rate or units takes the defaults.
    skipped = read_mapped_csv(path, parse_columns("gyr_x,gyr_y,gyr_z,acc_x,acc_y,acc_z", skip_columns=1))
    np.testing.assert_array_equal(skipped.samples, by_name.samples)
    sensor = read_csv_sensor(path, "mine", parse_columns("ax,ay,az,gx,gy,gz"))
    assert (sensor.sample_rate_hz, sensor.acc_unit, sensor.gyr_unit) == (60.0, "m/s^2", "rad/s")
    tabs = _write(tmp_path / "tabs.txt", path.read_text().replace(",", "\t"))
    by_tabs = read_mapped_csv(tabs, parse_columns("time_ms,gyr_x,gyr_y,gyr_z,acc_x,acc_y,acc_z,-"))
    np.testing.assert_array_equal(by_tabs.samples, by_position.samples)


def test_without_a_layout_the_reader_is_the_shared_one(tmp_path: Path) -> None:
    """No --columns: read_csv_imu as before (acc then gyr after --skip-columns), --rate and the units as given."""
    rows = np.column_stack([np.arange(40) / 100.0, np.tile([0.0, 0.0, 1.0, 10.0, 0.0, 0.0], (40, 1))])
    path = tmp_path / "left.csv"
    np.savetxt(path, rows, delimiter=",", header="time,ax,ay,az,gx,gy,gz", comments="")
    sensor = read_csv_sensor(path, "left", None, 1, 100.0, "g", "deg/s")
    np.testing.assert_array_equal(sensor.samples, read_csv_imu(path, 1))
    assert (sensor.sample_rate_hz, sensor.acc_unit, sensor.gyr_unit) == (100.0, "g", "deg/s")


# The Movella DOT app's export (its logger: "sep=," and one metadata line each, a blank line, the measurement
# mode's columns; rows with ", " between values), Custom Mode 5: quaternion, acc (m/s²), gyr (deg/s).
MOVELLA_DOT_HEAD = """sep=,
DeviceTag:,D422CD0049F2,,,,,,,,,,,,,,,,,
FirmwareVersion:,2.6.0,,,,,,,,,,,,,,,,,
AppVersion:,2023.6.0,,,,,,,,,,,,,,,,,
SyncStatus:,Synced,,,,,,,,,,,,,,,,,
OutputRate:,60Hz,,,,,,,,,,,,,,,,,
FilterProfile:,General,,,,,,,,,,,,,,,,,
Measurement Mode:,Custom Mode 5,,,,,,,,,,,,,,,,,
StartTime:,2023-05-01 10:00:00.000 +0200,,,,,,,,,,,,,,,,,
Movella Technologies B. V. 2005-2023,,,,,,,,,,,,,,,,,,,

PacketCounter,SampleTimeFine,Quat_W,Quat_X,Quat_Y,Quat_Z,Acc_X,Acc_Y,Acc_Z,Gyr_X,Gyr_Y,Gyr_Z
"""


def test_movella_dot_preset(tmp_path: Path) -> None:
    """SampleTimeFine in µs wraps at 2^32 (here mid-file) and one packet is missing: 60 Hz from the timestamps, the
    missing sample filled by resampling, acc m/s² and gyr deg/s."""
    t_us = (2**32 - 5 * 16667 + 16667 * np.arange(12)) % 2**32
    keep = np.arange(12) != 7
    rows = [
        f"{k + 1}, {int(t)}, 1.0, 0.0, 0.0, 0.0, 0.1, 0.2, {9.8 + k}, {10.0 * k}, 0.0, -1.5"
        for k, t in enumerate(t_us)
        if keep[k]
    ]
    path = _write(tmp_path / "D422CD0049F2_20230501_100000.csv", MOVELLA_DOT_HEAD + "\n".join(rows) + "\n")
    mapped = read_mapped_csv(path, PRESETS["movella-dot"])
    assert mapped.rate_hz == pytest.approx(60.0, rel=1e-3) and mapped.gaps == 1
    assert (mapped.acc_unit, mapped.gyr_unit) == ("m/s^2", "deg/s")
    expected = np.array([[0.1, 0.2, 9.8 + k, 10.0 * k, 0.0, -1.5] for k in range(12)])
    np.testing.assert_allclose(mapped.samples, expected, atol=1e-3)
    sensor = read_csv_sensor(path, "dot", PRESETS["movella-dot"], acc_unit="g")  # what is given wins
    assert (sensor.acc_unit, sensor.gyr_unit, sensor.sample_rate_hz) == ("g", "deg/s", pytest.approx(60.0, 1e-3))
    # A Sensor-fusion-mode export has no Acc or Gyr: the error says which columns were looked for.
    fusion = path.read_text().replace("Acc_X,Acc_Y,Acc_Z,Gyr_X,Gyr_Y,Gyr_Z", "FreeAcc_X,FreeAcc_Y,FreeAcc_Z,a,b,c")
    with pytest.raises(ColumnError, match="Acc_X, Acc_Y, Acc_Z, Gyr_X, Gyr_Y, Gyr_Z, SampleTimeFine"):
        read_mapped_csv(_write(tmp_path / "fusion.csv", fusion), PRESETS["movella-dot"])


# MT Manager 2019.2's text export as MovingReality's files have it (header lines copied from
# data/1019_pp01/Xsens/exported000/MT_012000E0_000-000_00B47786.txt): tab-separated, SampleTimeFine left empty.
MT_MANAGER_HEAD = (
    "// General information: \n//  MT Manager version: 2019.2.0 \n"
    "//  XDA version: 2019.2.0 build 3853 rev 94535 built on 2019-09-09\n// Device information: \n"
    "//  DeviceId: 00B47786\n//  ProductCode: MTW2-3A7G6\n//  Firmware Version: 4.6.0\n//  Hardware Version: 2.0.0\n"
    "// Device settings: \n//  Filter Profile: human(46.1)\n"
    "//  Option Flags: Orientation Smoother Disabled, AHS Disabled, ICC Disabled\n// Coordinate system: ENU\n"
)
MT_MANAGER_COLUMNS = (
    "PacketCounter\tSampleTimeFine\tAcc_X\tAcc_Y\tAcc_Z\tFreeAcc_E\tFreeAcc_N\tFreeAcc_U\tGyr_X\tGyr_Y\tGyr_Z\t"
    "Mag_X\tMag_Y\tMag_Z\tVelInc_X\tVelInc_Y\tVelInc_Z\tQuat_q0\tQuat_q1\tQuat_q2\tQuat_q3\tRoll\tPitch\tYaw\n"
)


def _mt_manager_rows(sample_time_fine: list[str]) -> str:
    rows = []
    for k, stf in enumerate(sample_time_fine):
        values = [60776 + k, stf, 9.75 + k, 0.15, -0.22, 0, 0, -0.05, 0.0067 * k, 0.007, -0.0085]
        values += [-0.97, 0.28, 0.30, 0.0975, 0.0015, -0.0022, 0.257, -0.66, -0.27, -0.65, 145.0, -88.4, 79.0]
        rows.append("\t".join(str(v) for v in values))
    return "\n".join(rows) + "\n"


def test_mt_manager_preset(tmp_path: Path) -> None:
    """SampleTimeFine in 10 kHz ticks gives the rate (100 Hz); an export that leaves it empty needs --rate (or an
    ``Update Rate`` header line); acc m/s² and gyr rad/s."""
    ticks = [str(1_000_000 + 100 * k) for k in range(20)]
    timed = _write(tmp_path / "MT_timed.txt", MT_MANAGER_HEAD + MT_MANAGER_COLUMNS + _mt_manager_rows(ticks))
    mapped = read_mapped_csv(timed, PRESETS["mt-manager"])
    assert (mapped.rate_hz, mapped.gaps, mapped.acc_unit, mapped.gyr_unit) == (
        pytest.approx(100.0),
        0,
        "m/s^2",
        "rad/s",
    )
    np.testing.assert_allclose(mapped.samples[3], [12.75, 0.15, -0.22, 0.0201, 0.007, -0.0085])
    untimed_text = MT_MANAGER_HEAD + MT_MANAGER_COLUMNS + _mt_manager_rows([""] * 20)
    untimed = _write(tmp_path / "MT_012000E0_000-000_00B47786.txt", untimed_text)
    assert read_mapped_csv(untimed, PRESETS["mt-manager"]).rate_hz is None
    with pytest.raises(ColumnError, match="gives no sample rate .* give --rate"):
        read_csv_sensor(untimed, "mt", PRESETS["mt-manager"])
    assert read_csv_sensor(untimed, "mt", PRESETS["mt-manager"], rate_hz=100.0).sample_rate_hz == 100.0
    stated = untimed.read_text().replace("// Coordinate system", "// Update Rate: 100.0Hz\n// Coordinate system")
    assert read_mapped_csv(_write(tmp_path / "MT_rate.txt", stated), PRESETS["mt-manager"]).rate_hz == 100.0


def test_column_layouts_that_cannot_be_read() -> None:
    with pytest.raises(ColumnError, match="each of acc_x, acc_y, acc_z, gyr_x, gyr_y, gyr_z exactly once"):
        parse_columns("acc_x,acc_y,acc_z,gyr_x,gyr_y,gyr_y")
    with pytest.raises(ColumnError, match="a preset \\(ximu3, movella-dot, mt-manager\\)"):
        parse_columns("Acc X,acc_y,acc_z,gyr_x,gyr_y,gyr_z")
    with pytest.raises(ColumnError, match="six header names"):
        parse_columns("ximu")


def _client(*args: str) -> subprocess.CompletedProcess:
    command = [sys.executable, "-m", "service.client", *args]
    return subprocess.run(command, capture_output=True, text=True, timeout=60, cwd=REPO)


def test_input_mistakes_are_one_line(tmp_path: Path) -> None:
    """A missing file, or a file that is not what the preset reads: one line on stderr, exit 2, no traceback."""
    missing = _client("--csv", "examples/ximu3_lowerbody/nope.csv")
    assert missing.returncode == 2 and "Traceback" not in missing.stderr, missing.stderr
    assert missing.stderr.strip() == "python -m service.client: error: examples/ximu3_lowerbody/nope.csv: no such file"
    wrong = _client("--preset", "movella-dot", "--csv", str(SAMPLE / "64F0EBCE.csv"))
    assert wrong.returncode == 2 and len(wrong.stderr.strip().splitlines()) == 1, wrong.stderr
    assert "expected a header row with the columns Acc_X" in wrong.stderr


@pytest.fixture(scope="module")
def server():
    proc, base = start_service(REPO / "onnx_models", threads=1)
    yield base.replace("http", "ws") + "/v1/stream"
    stop(proc)


def test_the_sample_streams_end_to_end(server: str, data_dir: Path, tmp_path: Path) -> None:
    """examples/README.md's command against a real server (as fast as possible, one JSON line per message): the
    joint assignment puts every file on the segment it was worn on, and the summary names it; then the same files
    through the live display into a recording console, whose table shows the same answer."""
    truth = _sample_truth(data_dir)
    files = [str(p.relative_to(REPO)) for p in sorted(SAMPLE.glob("*.csv"))]
    run = _client("--url", server, "--speed", "0", "--display", "json", "--preset", "ximu3", "--csv", *files)
    assert run.returncode == 0, run.stderr
    messages = [json.loads(line) for line in run.stdout.splitlines()]
    assert messages[0]["type"] == "started" and messages[-1]["type"] == "assignment"
    assert {s["sensor_id"]: s["segment"] for s in messages[-1]["sensors"]} == truth
    for serial, segment in truth.items():
        assert any(line.split()[:3] == [serial, "->", segment] for line in run.stderr.splitlines()), run.stderr

    args = _parser().parse_args(["--url", server, "--speed", "0", "--preset", "ximu3", "--csv", *files])
    console = Console(file=io.StringIO(), width=100, record=True, force_terminal=False)
    outcome = _stream(args, _sensors(args, _parser()), "live", console)
    assert outcome.close_code == 1000
    table = console.export_text()
    assert "status" in table and outcome.assignment["status"] in table
    for serial, segment in truth.items():
        row = next(line.split() for line in table.splitlines() if line.startswith(serial))
        assert row[4] == segment, row  # sensor, window, conf, moment, assigned


def test_the_live_table_follows_the_messages() -> None:
    """Notices and errors appear as they come; a still window's moment reads (still)."""
    view = LiveView(["a", "b"])
    view.update({"type": "started", "worn_segments": ["LeftFoot", "RightFoot"], "candidate_segments": {}})
    result = {"type": "result", "sensor_id": "a", "window_end_s": 2.1, "segment": "LeftFoot", "confidence": 0.75}
    view.update(result | {"moving": True})
    view.update({"type": "moment", "window_end_s": 2.1, "segments": {"a": "LeftFoot", "b": None}})
    view.update({"type": "gap", "sensor_id": "b", "expected_seq": 16, "received_seq": 48, "missing": 32})
    view.update({"type": "error", "detail": "sensor b: samples must be finite", "close_code": 1008})
    console = Console(file=io.StringIO(), width=100, record=True)
    console.print(view)
    text = console.export_text()
    assert "worn: LeftFoot, RightFoot" in text and "2.1 s answered" in text
    assert next(line for line in text.splitlines() if line.startswith("a ")).split()[1:4] == [
        "LeftFoot",
        "75%",
        "LeftFoot",
    ]
    assert "(still)" in next(line for line in text.splitlines() if line.startswith("b "))
    assert "1 gap" in text and "error: sensor b: samples must be finite (close code 1008)" in text
