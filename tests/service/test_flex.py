"""POST /v1/pose/flex and /v1/stream/flex on a test model whose answers a test can recompute (the mean of each
window times a matrix): one answer per sample once the calibration window is full, the stream equal to the
block, and every client mistake a 4xx or a close code that says what was expected."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from fastapi.testclient import TestClient
from starlette.websockets import WebSocketDisconnect

from service.api.protocol import encode_binary
from service.app import create_app
from service.core.opensim import read_opensim_storage
from service.settings import Settings
from tests.service.conftest import TINY_POSE, tiny_pose_weights, write_tiny_model, write_tiny_pose_model

CHANNELS, RATE, WINDOW, VALUE_RANGE, JOINTS, COMPONENTS = TINY_POSE["flex_pose"]


@pytest.fixture
def flex_client(tmp_path: Path):
    root = tmp_path / "onnx_models"
    write_tiny_model(root, "i2s_assignment")
    write_tiny_pose_model(root, "flex_pose")
    with TestClient(create_app(Settings(models_dir=root))) as c:
        yield c


def _block(n: int = WINDOW, seed: int = 0) -> np.ndarray:
    return np.random.default_rng(seed).integers(1000, 3000, size=(n, len(CHANNELS))).astype(float)


def _expected(x: np.ndarray) -> np.ndarray:
    """The test model's answer for every window ending at samples WINDOW-1 .. len(x)-1."""
    means = np.stack([x[e - WINDOW : e].mean(axis=0) for e in range(WINDOW, len(x) + 1)])
    return means @ tiny_pose_weights("flex_pose")


def test_flex_routes_answer_503_while_no_flex_model_is_loaded(client: TestClient) -> None:
    r = client.post("/v1/pose/flex", json={"samples": _block().tolist()})
    assert r.status_code == 503 and r.json()["detail"] == "no flex_pose model is loaded"
    with client.websocket_connect("/v1/stream/flex") as ws:
        assert ws.receive_json()["detail"] == "no flex_pose model is loaded"
        with pytest.raises(WebSocketDisconnect) as exc:
            ws.receive_json()
    assert exc.value.code == 1011


def test_every_sample_after_the_calibration_window_gets_its_angles(flex_client: TestClient) -> None:
    x = _block(130)
    r = flex_client.post("/v1/pose/flex", json={"samples": x.tolist(), "channels": CHANNELS})
    assert r.status_code == 200, r.text
    body = r.json()
    assert body["frames"] == 31 and body["first_sample"] == WINDOW - 1 and body["latency_samples"] == 0
    assert body["model"] == {"name": "flex_pose", "version": "0.0.1"}
    got = np.stack([body["angles_deg"][j]["flexion"] for j in JOINTS], axis=1)
    np.testing.assert_allclose(got, _expected(x), atol=2e-3)


def test_a_block_at_twice_the_rate_is_resampled_to_the_model_rate(flex_client: TestClient) -> None:
    x = np.repeat(_block(110), 2, axis=0)  # 220 readings at 40 Hz
    r = flex_client.post("/v1/pose/flex", json={"samples": x.tolist(), "sample_rate_hz": 2 * RATE})
    assert r.status_code == 200, r.text
    assert 9 <= r.json()["frames"] <= 11


@pytest.mark.parametrize(
    "body, fragment",
    [
        ({"samples": _block()[:, :3].tolist()}, "rows of 3 values"),
        ({"model": "flex_pose", "samples": _block()[:, :3].tolist()}, "every sample needs 4 values (left_elbow"),
        ({"samples": _block(99).tolist()}, "must cover the calibration window of 100 samples at 20 Hz (5 s)"),
        ({"samples": _block(150).tolist(), "sample_rate_hz": 40.0}, "at least 200 samples at 40 Hz; got 150"),
        ({"samples": np.full((100, 4), 5000.0).tolist()}, "samples[0]: values must lie in [0, 4095]"),
        ({"samples": np.full((100, 4), -1.0).tolist()}, "values must lie in [0, 4095]"),
        (
            {"samples": _block().tolist(), "sample_rate_hz": 0.5},
            "sample_rate_hz: Input should be greater than or equal to 1",
        ),
        ({"samples": _block().tolist(), "model": "nope"}, "no flex_pose model 'nope'"),
        ({"samples": _block().tolist(), "channels": CHANNELS[::-1]}, "takes ['left_elbow'"),
        ({"samples": _block(40_000).tolist()}, "at most 36000 samples at 20 Hz per request"),
    ],
)
def test_bad_flex_blocks_get_a_422_that_says_why(flex_client: TestClient, body: dict, fragment: str) -> None:
    r = flex_client.post("/v1/pose/flex", json=body)
    assert r.status_code == 422
    assert fragment in r.json()["detail"], r.json()["detail"]


def test_a_nan_reading_is_named(flex_client: TestClient) -> None:
    x = _block()
    x[42, 1] = np.nan
    text = json.dumps({"samples": x.tolist()})  # NaN literals: valid for Python's json, not for the standard
    r = flex_client.post("/v1/pose/flex", content=text, headers={"content-type": "application/json"})
    assert r.status_code == 422 and "samples[42]: samples must be finite" in r.json()["detail"]


def _stream(ws, packets: list[tuple[int, np.ndarray]], binary: bool = False) -> list[dict]:
    for seq, rows in packets:
        if binary:
            ws.send_bytes(encode_binary(0, seq, rows))
        else:
            ws.send_json({"type": "samples", "seq": seq, "samples": rows.tolist()})
    ws.send_json({"type": "stop"})
    out = []
    while True:
        try:
            out.append(ws.receive_json())
        except WebSocketDisconnect:
            return out


@pytest.mark.parametrize("binary", [False, True])
def test_the_stream_answers_as_the_block_does(flex_client: TestClient, binary: bool) -> None:
    x = _block(160, seed=3)
    with flex_client.websocket_connect("/v1/stream/flex") as ws:
        ws.send_json({"type": "start", "channels": CHANNELS})
        started = ws.receive_json()
        assert started["type"] == "started" and started["window_samples"] == WINDOW and started["joints"] == JOINTS
        messages = _stream(ws, [(k, x[k : k + 7]) for k in range(0, 160, 7)], binary)
    angles = [m for m in messages if m["type"] == "angles"]
    assert angles[0]["first_sample"] == WINDOW - 1
    got = np.concatenate([np.asarray(m["angles_deg"])[:, :, 0] for m in angles])
    np.testing.assert_allclose(got, _expected(x.astype(np.float32)), atol=2e-3)


def test_a_stream_at_twice_the_model_rate_is_averaged_pairwise(flex_client: TestClient) -> None:
    x = _block(120, seed=4)
    fast = np.repeat(x, 2, axis=0)
    with flex_client.websocket_connect("/v1/stream/flex") as ws:
        ws.send_json({"type": "start", "channels": CHANNELS, "sample_rate_hz": 2 * RATE})
        assert ws.receive_json()["decimation"] == 2
        messages = _stream(ws, [(k, fast[k : k + 9]) for k in range(0, len(fast), 9)])
    got = np.concatenate([np.asarray(m["angles_deg"])[:, :, 0] for m in messages if m["type"] == "angles"])
    np.testing.assert_allclose(got, _expected(x), atol=2e-3)


def test_a_gap_restarts_the_calibration_window_and_says_so(flex_client: TestClient) -> None:
    x = _block(400, seed=5)
    with flex_client.websocket_connect("/v1/stream/flex") as ws:
        ws.send_json({"type": "start", "channels": CHANNELS})
        ws.receive_json()
        messages = _stream(ws, [(0, x[:120]), (150, x[150:260]), (100, x[100:110]), (250, x[250:270])])
    kinds = [m["type"] for m in messages]
    assert kinds == ["angles", "gap", "angles", "late", "late", "angles"], kinds
    assert messages[1]["missing"] == 30 and messages[2]["first_sample"] == 150 + 99  # in the stream's time
    assert messages[2]["frames"] == 11 and messages[3]["samples_dropped"] == 10
    # a packet that overlaps: its 10 repeated readings dropped, its 10 new ones answered in turn
    assert messages[4]["samples_dropped"] == 10 and messages[5]["first_sample"] == 260 and messages[5]["frames"] == 10


@pytest.mark.parametrize(
    "start, packet, code, fragment",
    [
        ({"type": "start", "channels": ["a", "b"]}, None, 1008, "name one of the loaded flex models"),
        ({"type": "start", "model": "flex_pose", "channels": CHANNELS[::-1]}, None, 1008, "in this order"),
        ({"type": "start", "channels": CHANNELS, "sample_rate_hz": 30.0}, None, 1008, "an integer multiple"),
        (
            {"type": "start", "channels": CHANNELS},
            {"type": "samples", "seq": 100, "samples": [[1, 2, 3]]},
            1008,
            "every sample needs 4 values",
        ),
        (
            {"type": "start", "channels": CHANNELS},
            {"type": "samples", "seq": 100, "samples": [[1, 2, 3, 5000]]},
            1008,
            "packet seq 100: samples[0]: values must lie in [0, 4095]",
        ),
    ],
)
def test_stream_mistakes_close_with_what_was_expected(flex_client, start, packet, code, fragment) -> None:
    x = _block(100, seed=6)
    with flex_client.websocket_connect("/v1/stream/flex") as ws:
        ws.send_json(start)
        if packet is not None:
            assert ws.receive_json()["type"] == "started"
            ws.send_json({"type": "samples", "seq": 0, "samples": x.tolist()})  # accepted: its answer must come
            ws.send_json(packet)
        messages = []
        with pytest.raises(WebSocketDisconnect) as exc:
            while True:
                messages.append(ws.receive_json())
    assert exc.value.code == code
    assert fragment in messages[-1]["detail"], messages[-1]
    if packet is not None:
        assert [m["type"] for m in messages] == ["angles", "error"]


def test_models_endpoint_lists_the_flex_contract(flex_client: TestClient) -> None:
    flex = flex_client.get("/v1/models").json()["flex_pose"]
    manifest = flex["manifest"] if "manifest" in flex else flex
    assert manifest["channels"][0] == "left_elbow" and manifest["joints"][0] == "LeftElbow"
    assert manifest["value_range"] == [0.0, 4095.0] and manifest["flex"]["latency_samples"] == 0


def test_a_flex_manifest_that_does_not_describe_its_tensors_is_refused(tmp_path: Path) -> None:
    from service.core.manifest import read_manifest
    from service.inference.registry import load_models

    root = tmp_path / "onnx_models"
    target = write_tiny_pose_model(root, "flex_pose")
    manifest = read_manifest(target / "manifest.json").model_dump()
    manifest["joints"] = manifest["joints"][:3]  # the output has 4 joints
    (target / "manifest.json").write_text(json.dumps(manifest))
    with pytest.raises(ValueError, match=r"output of shape \['batch', 3, 1\]"):
        read_manifest(target / "manifest.json")
    manifest["joints"] = JOINTS
    manifest["flex"] = None
    (target / "manifest.json").write_text(json.dumps(manifest))
    with pytest.raises(ValueError, match="needs a 'flex' section"):
        read_manifest(target / "manifest.json")
    assert load_models(root, 1) == {}  # refused with a log line, nothing served


def test_live_sessions_batched_together_answer_as_each_alone(flex_client: TestClient) -> None:
    """The live flex batches (``process_live_flex``): sessions at different points of their streams, some with a
    full window and some still filling it, answered in one network call exactly as one by one."""
    from service.inference.flex import LiveFlex, process_live_flex

    model = flex_client.app.state.flex_models["flex_pose"]
    blocks = [_block(160, seed) for seed in range(4)]
    alone = [LiveFlex(model, 1) for _ in blocks]
    together = [LiveFlex(model, 1) for _ in blocks]
    starts = [0, 40, 90, 130]  # where each session's stream is when the batches start
    for live_a, live_b, x, s in zip(alone, together, blocks, starts, strict=True):
        live_a.push(x[:s])
        live_b.push(x[:s])
    for k in range(3):
        parts = [x[s + 10 * k : s + 10 * (k + 1)] for x, s in zip(blocks, starts, strict=True)]
        batched = process_live_flex([(live, rows) for live, rows in zip(together, parts, strict=True)])
        for live, rows, (first, angles) in zip(alone, parts, batched, strict=True):
            first_alone, angles_alone = live.push(rows)
            assert first == first_alone
            np.testing.assert_allclose(angles, angles_alone, atol=1e-5)
    assert [len(a) for _, a in batched] == [0, 0, 10, 10]  # two still fill their window, two answer every sample


def test_a_live_flex_stream_runs_in_the_batcher_measured_at_start_up(flex_client: TestClient) -> None:
    """A stream goes through the service's flex batcher, whose model cost the start-up probe measured."""
    batcher = flex_client.app.state.flex_batcher
    before = len(batcher.batches)
    x = _block(130, 3)
    with flex_client.websocket_connect("/v1/stream/flex") as ws:
        ws.send_text(json.dumps({"type": "start", "model": "flex_pose", "channels": CHANNELS}))
        assert json.loads(ws.receive_text())["type"] == "started"
        ws.send_bytes(encode_binary(0, 0, x.astype(np.float32)))
        message = json.loads(ws.receive_text())
        ws.send_text(json.dumps({"type": "stop"}))
    np.testing.assert_allclose(np.asarray(message["angles_deg"])[:, :, 0], _expected(x), atol=2e-3)
    assert len(batcher.batches) > before
    assert flex_client.app.state.streams.seconds_per_frame["flex_pose"] > 0


def test_flex_sessions_are_refused_while_the_flex_answers_rise(flex_client: TestClient, monkeypatch) -> None:
    """As for pose sessions: while the live flex answers of the last second pass 35 % of the latency target at p99
    (the load still rising), a new flex session is refused with 1013 and the reason; I2S answers that wait for
    company in their micro-batches do not count."""
    import service.api.stream_admission as stream_admission

    monkeypatch.setattr(stream_admission, "RISING_WINDOW_S", 3.0)  # room for a slow machine
    admission = flex_client.app.state.streams
    start = json.dumps({"type": "start", "model": "flex_pose", "channels": CHANNELS})
    with flex_client.websocket_connect("/v1/stream/flex") as first:
        first.send_text(start)
        assert json.loads(first.receive_text())["type"] == "started"
        for _ in range(60):
            admission.observe_latency(0.03, flex=True)  # within a third of the target
            admission.observe_latency(0.07)  # I2S answers: not counted here
        with flex_client.websocket_connect("/v1/stream/flex") as ws:
            ws.send_text(start)
            assert json.loads(ws.receive_text())["type"] == "started"
            ws.send_text(json.dumps({"type": "stop"}))
        for _ in range(60):
            admission.observe_latency(0.07, flex=True)  # rising past 35 % of it
        assert admission.recent_p99_ms() < admission.latency_target_ms
        with flex_client.websocket_connect("/v1/stream/flex") as ws:
            ws.send_text(start)
            error = json.loads(ws.receive_text())
        assert error["close_code"] == 1013 and "flex answers of the last second take 70 ms" in error["detail"], error
        first.send_text(json.dumps({"type": "stop"}))


def test_readings_that_look_like_volts_or_a_dead_channel_are_answered_with_warnings(flex_client: TestClient) -> None:
    """Volts (or 0–1 values) where the model takes 12-bit counts, and a channel that reads one value over the whole
    calibration window, pass the range check; the angles are answered with warnings that say what it looks like,
    on REST and once on the stream. Plausible counts get none."""
    volts = np.random.default_rng(6).uniform(0.5, 2.5, size=(WINDOW + 10, len(CHANNELS)))
    r = flex_client.post("/v1/pose/flex", json={"samples": volts.tolist()})
    assert r.status_code == 200, r.text
    assert r.json()["frames"] == 11
    (warning,) = r.json()["warnings"]
    assert "at most 2.5" in warning and "volts or 0–1 values" in warning, warning

    dead = _block(WINDOW + 10, seed=7)
    dead[:, 1] = 4095.0
    (warning,) = flex_client.post("/v1/pose/flex", json={"samples": dead.tolist()}).json()["warnings"]
    assert f"channel {CHANNELS[1]} reads 4095 (the end of the value range" in warning, warning
    assert flex_client.post("/v1/pose/flex", json={"samples": _block(WINDOW + 10).tolist()}).json()["warnings"] == []
    # judged on the rows as sent: resampling a block sent at 5 times the model's rate would blur the dead channel
    fast = np.repeat(dead, 5, axis=0)
    r = flex_client.post("/v1/pose/flex", json={"samples": fast.tolist(), "sample_rate_hz": 5 * RATE})
    assert r.status_code == 200, r.text
    (warning,) = r.json()["warnings"]
    assert f"channel {CHANNELS[1]} reads 4095 (the end of the value range" in warning, warning

    with flex_client.websocket_connect("/v1/stream/flex") as ws:
        ws.send_json({"type": "start", "channels": CHANNELS})
        ws.receive_json()
        messages = _stream(ws, [(k, dead[k : k + 7]) for k in range(0, len(dead), 7)])
    warnings = [m for m in messages if m["type"] == "warning"]
    assert len(warnings) == 1 and CHANNELS[1] in warnings[0]["warnings"][0], messages
    first_angles = next(i for i, m in enumerate(messages) if m["type"] == "angles")
    assert messages.index(warnings[0]) < first_angles  # with the first answers, not after the stream


def test_the_angles_come_as_an_opensim_storage_file(flex_client: TestClient) -> None:
    """``format=mot``: the JSON answer's angles as an OpenSim storage file, time in seconds from the block's first
    sample; model and warnings in the headers; an unknown format is a 422 naming the known ones."""
    x = _block(130)
    as_json = flex_client.post("/v1/pose/flex", json={"samples": x.tolist()}).json()
    r = flex_client.post("/v1/pose/flex", params={"format": "mot"}, json={"samples": x.tolist()})
    assert r.status_code == 200, r.text
    assert r.headers["x-flex-model"] == "flex_pose 0.0.1" and json.loads(r.headers["x-flex-warnings"]) == []
    assert 'filename="flex_pose.mot"' in r.headers["content-disposition"]
    header, names, table = read_opensim_storage(r.text, "answer")
    assert header["inDegrees"] == "yes" and int(header["nRows"]) == len(table) == as_json["frames"] == 31
    assert names == ["time"] + [f"{j}_{c}" for j in JOINTS for c in COMPONENTS]
    np.testing.assert_allclose(table[:, 0], (WINDOW - 1 + np.arange(31)) / RATE, atol=1e-6)
    want = np.stack([as_json["angles_deg"][j][c] for j in JOINTS for c in COMPONENTS], axis=1)
    np.testing.assert_allclose(table[:, 1:], want, atol=2e-3)
    volts = np.random.default_rng(6).uniform(0.5, 2.5, size=(WINDOW + 10, len(CHANNELS)))
    r = flex_client.post("/v1/pose/flex", params={"format": "mot"}, json={"samples": volts.tolist()})
    assert "volts" in json.loads(r.headers["x-flex-warnings"])[0]
    bad = flex_client.post("/v1/pose/flex", params={"format": "csv"}, json={"samples": x.tolist()})
    assert bad.status_code == 422 and "'json' or 'mot'" in bad.text


def test_a_file_answer_lists_at_most_eight_warnings_in_its_header() -> None:
    from service.api.routes import file_answer

    r = file_answer("x", "a.mot", "Flex", "m", "1.0.0", [f"warning {k} " + "y" * 300 for k in range(20)])
    shown = json.loads(r.headers["x-flex-warnings"])
    assert len(shown) == 9 and shown[-1].startswith("(and 12 more") and all(len(w) < 230 for w in shown[:8])
    assert r.headers["x-flex-model"] == "m 1.0.0" and r.body == b"x"
