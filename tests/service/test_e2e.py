"""End to end: a real uvicorn server with the shipped models, a real WebSocket client streaming a real
recording (seven x-IMU3 sensors), and the same windows over REST: the results must agree."""

from __future__ import annotations

import asyncio
import json
import subprocess
import sys
from pathlib import Path

import httpx
import numpy as np
import pytest
import websockets

from benchmarks.servers import REPO, server_log, start_service, stop
from service.api.protocol import encode_binary
from service.client import ClientSensor, stream_sensors
from service.core.recordings import read_recording
from service.core.segments import BODY_PART, SEGMENTS
from service.core.windowing import sliding_windows

# A dynamic-int8 LSTM quantises its inputs per call, so a window's alignment moves with its batch: up to 0.8–1.05°
# with 2.1.0 and 3.6° with such a 3.x file. The served 3.17.0 (as 3.11.0, 3.9.0, 3.5.0, 3.3.0 and 3.1.0) keeps its
# LSTM in float32.
MAX_BATCHING_ANGLE_DEG = 2.0


@pytest.fixture(scope="module")
def server():
    proc, base = start_service(REPO / "onnx_models", threads=1)
    yield base
    stop(proc)


# The served assignment model trained on every real recording of the data directory; what the per-moment answers
# and the declarations add on people a model never saw is measured with 1.9.0 (served before it; two networks
# trained on simulated data only).
UNSEEN_ASSIGNMENT = "1.9.0"


@pytest.fixture(scope="module")
def unseen_server(tmp_path_factory: pytest.TempPathFactory):
    """The served models plus the archived 1.9.0, brought back as a user would (``training.cli restore-model``)."""
    from training.snapshot import restore_model

    models = tmp_path_factory.mktemp("models")
    for served in (REPO / "onnx_models").glob("*/*/manifest.json"):
        (models / served.parent.parent.name).mkdir(exist_ok=True)
        (models / served.parent.parent.name / served.parent.name).symlink_to(served.parent)
    restore_model("i2s_assignment", UNSEEN_ASSIGNMENT, REPO / "mlflow_snapshot", models)
    # These tests measure answers, not admission: streams may take the whole measured capacity, so that 1.9.0 (16
    # passes a window, about 44 windows/s on one slow shared core) admits a seven-sensor stream (26 windows/s).
    proc, base = start_service(
        models, threads=1, model_versions=f"i2s_assignment={UNSEEN_ASSIGNMENT}", stream_capacity_fraction="1.0"
    )
    assert httpx.get(f"{base}/v1/models").json()["i2s_assignment"]["version"] == UNSEEN_ASSIGNMENT
    yield base
    stop(proc)


def test_shipped_models_are_served(server: str) -> None:
    models = httpx.get(f"{server}/v1/models").json()
    assert {"i2s_assignment", "i2s_alignment"} <= set(models)


def test_stream_equals_rest_and_reports_joint_assignment(server: str, data_dir: Path) -> None:
    rec = read_recording(data_dir, "ximu3_lowerbody")
    sensors = [ClientSensor(s.sensor_id, s.imu[:400]) for s in rec.sensors]
    outcome = asyncio.run(stream_sensors(server.replace("http", "ws") + "/v1/stream", sensors, speed=0))
    assert outcome.close_code == 1000
    per_sensor = {s.sensor_id: [r for r in outcome.results if r["sensor_id"] == s.sensor_id] for s in sensors}
    angles = []
    for s in sensors:
        windows = sliding_windows(s.samples.astype(np.float32))
        streamed = per_sensor[s.sensor_id]
        assert len(streamed) == len(windows)
        body = {"windows": [{"samples": w.tolist()} for w in windows]}
        rest = httpx.post(f"{server}/v1/imu/windows", json=body, timeout=30).json()["results"]
        for a, b in zip(streamed, rest, strict=True):
            assert a["segment"] == b["segment"]
            np.testing.assert_allclose(
                [a["probabilities"][k] for k in SEGMENTS], [b["probabilities"][k] for k in SEGMENTS], atol=1e-4
            )
            # The shipped int8 alignment model quantises its LSTM inputs per onnxruntime call (dynamic int8), so a
            # window's quaternion moves a little with the windows that share its call: compared as an angle.
            dot = abs(float(np.dot(a["alignment"]["q_segment_imu"], b["alignment"]["q_segment_imu"])))
            angles.append(np.degrees(2 * np.arccos(min(dot, 1.0))))
    print(f"stream vs REST alignment: max {max(angles):.3f} deg, median {np.median(angles):.4f} deg")
    assert max(angles) < MAX_BATCHING_ANGLE_DEG
    final = outcome.assignment["sensors"]
    assert len(final) == 7 and all(s["segment"] in SEGMENTS for s in final)
    assert len({s["segment"] for s in final}) == 7  # one-to-one
    # The stream's settled alignment per sensor is /v1/imu/assign's robust mean over the same windows.
    body = {
        "sensors": [
            {"sensor_id": s.sensor_id, "windows": [{"samples": w.tolist()} for w in sliding_windows(s.samples)]}
            for s in sensors
        ]
    }
    assigned = httpx.post(f"{server}/v1/imu/assign", json=body, timeout=60).json()["sensors"]
    # One moment message per window end time, each the per-moment answer /v1/imu/assign gives the same windows.
    n_windows = len(sliding_windows(sensors[0].samples))
    assert [m["window_end_s"] for m in outcome.moments] == [round((127 + 16 * k) / 60.0, 6) for k in range(n_windows)]
    for k, moment in enumerate(outcome.moments):
        assert moment["segments"] == {s["sensor_id"]: s["window_segments"][k] for s in assigned}
    for got, want in zip(final, assigned, strict=True):
        assert (got["sensor_id"], got["segment"]) == (want["sensor_id"], want["segment"])
        assert got["alignment"]["segment"] == got["segment"]
        dot = abs(float(np.dot(got["alignment"]["q_segment_imu"], want["alignment"]["q_segment_imu"])))
        assert np.degrees(2 * np.arccos(min(dot, 1.0))) < MAX_BATCHING_ANGLE_DEG
        assert got["alignment_spread_deg"] == pytest.approx(want["alignment_spread_deg"], abs=MAX_BATCHING_ANGLE_DEG)
    metrics = httpx.get(f"{server}/metrics").text
    assert "wearmocap_stream_samples_total 2800.0" in metrics


def test_shipped_alignment_is_stable_on_a_real_recording(server: str, data_dir: Path) -> None:
    """x-IMU3 (a person and sensors never trained on): joint assignment right for all seven sensors, and the
    alignment of each leg and foot sensor stable over its windows (a strapped sensor does not turn). Measured
    with 2.1.0: 4–13° for these six; the pelvis is unstable (51°) and left out (README: known weakness)."""
    rec = read_recording(data_dir, "ximu3_lowerbody")
    body = {
        "sensors": [
            {"sensor_id": s.sensor_id, "windows": [{"samples": w.tolist()} for w in sliding_windows(s.imu)[:40]]}
            for s in rec.sensors
        ]
    }
    out = httpx.post(f"{server}/v1/imu/assign", json=body, timeout=60).json()["sensors"]
    for s, got in zip(rec.sensors, out, strict=True):
        assert got["segment"] == SEGMENTS[s.segment], (s.sensor_id, got["segment"])
        if got["segment"] != "Pelvis":
            assert got["alignment_spread_deg"] < 15.0, (s.sensor_id, got["alignment_spread_deg"])


def test_assign_answers_each_moment_of_a_real_recording_one_to_one(unseen_server: str, data_dir: Path) -> None:
    """The capacitive subject's stiff-knee trial (never trained on), 100 windows of each of the seven leg and pelvis
    sensors: the per-moment answers of /v1/imu/assign are right far more often than each window's own answer
    (measured with 1.9.0: 88.7 % own, 99.7 % per moment; the torso sensor, off the seven segments, is left out)."""
    rec = read_recording(data_dir, "capacitive_sub01/CSStiffKnee")
    sensors = [s for s in rec.sensors if s.segment is not None]
    windows = {s.sensor_id: [{"samples": w.tolist()} for w in sliding_windows(s.imu)[50:150]] for s in sensors}
    body = {"sensors": [{"sensor_id": k, "windows": w} for k, w in windows.items()]}
    assigned = httpx.post(f"{unseen_server}/v1/imu/assign", json=body, timeout=120).json()["sensors"]
    own, at_moment = [], []
    for s, got in zip(sensors, assigned, strict=True):
        results = httpx.post(f"{unseen_server}/v1/imu/windows", json={"windows": windows[s.sensor_id]}, timeout=120)
        moving = [r for r in results.json()["results"] if r["moving"]]
        own += [r["segment"] == SEGMENTS[s.segment] for r in moving]
        at_moment += [g == SEGMENTS[s.segment] for g in got["window_segments"] if g is not None]
        assert len(at_moment) == len(own)  # exactly the moving windows get a per-moment answer
    print(f"own {np.mean(own):.3f}, per moment {np.mean(at_moment):.3f} of {len(own)} moving windows")
    assert np.mean(at_moment) >= 0.97 and np.mean(at_moment) >= np.mean(own) + 0.05


def test_declaring_the_feet_settles_which_foot_is_which(unseen_server: str, data_dir: Path) -> None:
    """gaitmap's 4 × 10 m walk, two foot sensors (a person and sensors never trained on). Over all seven segments
    the served model takes the right foot for a shank at most moments (1.9.0: 64 % of moving windows right per
    moment); told that the sensors are on the feet, it only has to say which foot, and is right at almost every
    moment (99.6 % measured), over REST and over a real WebSocket stream alike."""
    rec = read_recording(data_dir, "gaitmap_foot/imu_sample_ic_stride")
    feet = ["LeftFoot", "RightFoot"]
    truth = {s.sensor_id: SEGMENTS[s.segment] for s in rec.sensors}
    body = {
        "sensors": [
            {"sensor_id": s.sensor_id, "windows": [{"samples": w.tolist()} for w in sliding_windows(s.imu)]}
            for s in rec.sensors
        ]
    }

    def per_moment(answer: list[dict]) -> float:
        right = [g == truth[s["sensor_id"]] for s in answer for g in s["window_segments"] if g is not None]
        return float(np.mean(right))

    free = httpx.post(f"{unseen_server}/v1/imu/assign", json=body, timeout=120).json()["sensors"]
    declared = httpx.post(f"{unseen_server}/v1/imu/assign", json=body | {"worn_segments": feet}, timeout=120).json()
    declared = declared["sensors"]
    print(f"per moment: {per_moment(free):.3f} over seven segments, {per_moment(declared):.3f} declared as feet")
    assert {g for s in declared for g in s["window_segments"]} <= set(feet) | {None}
    assert all(s["segment"] == truth[s["sensor_id"]] for s in declared)
    assert per_moment(declared) >= 0.98 and per_moment(declared) >= per_moment(free) + 0.2
    sensors = [ClientSensor(s.sensor_id, s.imu) for s in rec.sensors]
    url = unseen_server.replace("http", "ws") + "/v1/stream"
    outcome = asyncio.run(stream_sensors(url, sensors, speed=0, worn_segments=feet))
    assert outcome.close_code == 1000
    assert next(e for e in outcome.events if e["type"] == "started")["worn_segments"] == feet
    for k, moment in enumerate(outcome.moments):
        assert moment["segments"] == {s["sensor_id"]: s["window_segments"][k] for s in declared}
    assert {s["sensor_id"]: s["segment"] for s in outcome.assignment["sensors"]} == truth


def test_declaring_body_parts_leaves_only_the_side_to_find(unseen_server: str, data_dir: Path) -> None:
    """The x-IMU3 person, seven sensors, each declared on its body part with the side unknown (``candidate_segments``:
    both feet, both shanks, both thighs, or the pelvis). Every answer stays among the sensor's candidates, the
    per-moment answers beat the undeclared ones (1.9.0 on its moving windows: 75.6 % → 80.3 %, manifest
    ``window_joint_part_accuracy``), and the live stream's moments and joint answer equal the REST ones."""
    rec = read_recording(data_dir, "ximu3_lowerbody")
    truth = {s.sensor_id: SEGMENTS[s.segment] for s in rec.sensors}
    sides = {
        s.sensor_id: [n for n in SEGMENTS if BODY_PART[SEGMENTS.index(n)] == BODY_PART[s.segment]] for s in rec.sensors
    }
    free = {
        "sensors": [
            {"sensor_id": s.sensor_id, "windows": [{"samples": w.tolist()} for w in sliding_windows(s.imu)]}
            for s in rec.sensors
        ]
    }
    declared = {"sensors": [s | {"candidate_segments": sides[s["sensor_id"]]} for s in free["sensors"]]}

    def per_moment(answer: list[dict]) -> float:
        right = [g == truth[s["sensor_id"]] for s in answer for g in s["window_segments"] if g is not None]
        return float(np.mean(right))

    before = httpx.post(f"{unseen_server}/v1/imu/assign", json=free, timeout=120).json()["sensors"]
    after = httpx.post(f"{unseen_server}/v1/imu/assign", json=declared, timeout=120).json()["sensors"]
    print(f"per moment: {per_moment(before):.3f} undeclared, {per_moment(after):.3f} with body parts declared")
    for s in after:
        assert {g for g in s["window_segments"] if g is not None} | {s["segment"]} <= set(sides[s["sensor_id"]])
        assert (s["margin"] is None) == (len(sides[s["sensor_id"]]) == 1)
    assert per_moment(after) >= per_moment(before) + 0.03
    sensors = [ClientSensor(s.sensor_id, s.imu, candidate_segments=sides[s.sensor_id]) for s in rec.sensors]
    outcome = asyncio.run(stream_sensors(unseen_server.replace("http", "ws") + "/v1/stream", sensors, speed=0))
    assert outcome.close_code == 1000
    assert next(e for e in outcome.events if e["type"] == "started")["candidate_segments"] == sides
    for k, moment in enumerate(outcome.moments):
        assert moment["segments"] == {s["sensor_id"]: s["window_segments"][k] for s in after}
    assert {s["sensor_id"]: s["segment"] for s in outcome.assignment["sensors"]} == {
        s["sensor_id"]: s["segment"] for s in after
    }
    assert {s["sensor_id"]: s["segment"] for s in after} == truth


def test_the_client_streams_csv_files_with_declared_feet(server: str, data_dir: Path, tmp_path: Path) -> None:
    """`python -m service.client --csv … --worn …`, the README's "try your own IMUs" path, as a subprocess: the
    gaitmap walk's two feet as CSV files in g and deg/s with a time column; every moment names only feet, and the
    final assignment puts each file on its foot."""
    rec = read_recording(data_dir, "gaitmap_foot/imu_sample_ic_stride")
    args = [sys.executable, "-m", "service.client", "--url", server.replace("http", "ws") + "/v1/stream"]
    args += ["--rate", "60", "--acc-unit", "g", "--gyr-unit", "deg/s", "--skip-columns", "1", "--speed", "0"]
    args += ["--out", str(tmp_path / "out.jsonl")]
    for s in rec.sensors:
        t = np.arange(len(s.imu)) / 60.0
        rows = np.column_stack([t, s.imu[:, :3] / 9.80665, np.degrees(s.imu[:, 3:])])
        path = tmp_path / f"{SEGMENTS[s.segment]}.csv"
        np.savetxt(path, rows, delimiter=",", header="time,ax,ay,az,gx,gy,gz", comments="")
        args += ["--csv", str(path)]
    feet = ["--worn", "LeftFoot", "--worn", "RightFoot"]
    done = subprocess.run([*args, *feet], capture_output=True, text=True, timeout=120, cwd=REPO)
    assert done.returncode == 0, done.stderr
    messages = [json.loads(line) for line in (tmp_path / "out.jsonl").read_text().splitlines()]
    moments = [m for m in messages if m["type"] == "moment"]
    assert moments and {g for m in moments for g in m["segments"].values()} <= {"LeftFoot", "RightFoot", None}
    for name in ("LeftFoot", "RightFoot"):  # the log line of the final assignment: file name -> segment
        assert any(line.split()[:3] == [name, "->", name] for line in done.stderr.splitlines()), done.stderr
    # One sensor declared the pelvis by --candidates: the server echoes it and puts that file on the pelvis.
    pelvis = subprocess.run([*args, "--candidates", "LeftFoot=Pelvis"], capture_output=True, text=True, timeout=120)
    assert pelvis.returncode == 0, pelvis.stderr
    assert "'candidate_segments': {'LeftFoot': ['Pelvis'], 'RightFoot': None}" in pelvis.stderr, pelvis.stderr
    assert any(line.split()[:3] == ["LeftFoot", "->", "Pelvis"] for line in pelvis.stderr.splitlines())
    unknown = subprocess.run([*args, "--candidates", "Head=Pelvis"], capture_output=True, text=True, timeout=60)
    assert unknown.returncode == 2 and "--candidates takes SENSOR=SEGMENT,SEGMENT" in unknown.stderr
    # Declarations that contradict each other: the server closes with 1008 and says why; the client exits 1.
    clash = subprocess.run(
        [*args, *feet, "--candidates", "LeftFoot=Pelvis"], capture_output=True, text=True, timeout=60
    )
    assert clash.returncode == 1 and "none of ['Pelvis'] is among worn_segments" in clash.stderr, clash.stderr


def test_clients_that_vanish_mid_stream_leave_no_server_errors(server: str) -> None:
    """One client aborts its TCP connection and one closes cleanly while results are still being computed;
    the server logs no application error, closes both sessions and goes on serving."""
    url = server.replace("http", "ws") + "/v1/stream"
    samples = np.tile(np.array([0.0, 0.0, 9.81, 0.1, 0.0, 0.0], dtype=np.float32), (256, 1))

    async def leave(abort: bool) -> None:
        async with websockets.connect(url) as ws:
            await ws.send(json.dumps({"type": "start", "sensors": [{"sensor_id": "s"}]}))
            await ws.recv()
            for first in range(0, 256, 16):
                await ws.send(encode_binary(0, first, samples[first : first + 16]))
            if abort:
                ws.transport.abort()

    async def both() -> None:
        await asyncio.gather(leave(abort=True), leave(abort=False))
        await asyncio.sleep(0.5)

    asyncio.run(both())
    metrics = httpx.get(f"{server}/metrics").text
    assert "wearmocap_open_streams 0.0" in metrics
    log = server_log(server).read_text()
    assert "Exception in ASGI application" not in log, log[-3000:]
    assert "Task exception was never retrieved" not in log, log[-3000:]
