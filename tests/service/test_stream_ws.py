"""WebSocket protocol with the TestClient: results, gaps, binary packets and the close codes."""

from __future__ import annotations

import json

import numpy as np
import pytest
from fastapi.testclient import TestClient
from starlette.websockets import WebSocketDisconnect

from service.api.protocol import encode_binary
from service.app import create_app
from service.settings import Settings

START = {"type": "start", "sensors": [{"sensor_id": "a"}, {"sensor_id": "b", "sample_rate_hz": 120.0}]}


def _signal(n: int, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    x = rng.normal(size=(n, 6))
    x[:, 2] += 9.81
    x[:, 3:] *= 2.0
    return x


def _collect(ws, until: str = "close") -> list[dict]:
    out = []
    try:
        while True:
            out.append(json.loads(ws.receive_text()))
    except WebSocketDisconnect as exc:
        out.append({"type": "close", "code": exc.code, "reason": exc.reason})
    return out


def test_stream_results_assignment_and_stop(client: TestClient) -> None:
    x = _signal(160)
    with client.websocket_connect("/v1/stream") as ws:
        ws.send_text(json.dumps(START))
        assert json.loads(ws.receive_text())["type"] == "started"
        for seq in range(0, 160, 16):
            ws.send_text(
                json.dumps({"type": "samples", "sensor_id": "a", "seq": seq, "samples": x[seq : seq + 16].tolist()})
            )
        ws.send_bytes(encode_binary(1, 0, _signal(300, 1)))
        ws.send_text(json.dumps({"type": "stop"}))
        messages = _collect(ws)
    results = [m for m in messages if m["type"] == "result"]
    assert [r["sensor_id"] for r in results].count("a") == 3  # windows at 0, 16, 32 (160 samples)
    assert [r["sensor_id"] for r in results].count("b") == 2  # 300 samples at 120 Hz -> 150 at 60 Hz
    final = [m for m in messages if m["type"] == "assignment"][-1]
    assert {s["sensor_id"] for s in final["sensors"]} == {"a", "b"}
    assert messages[-1] == {"type": "close", "code": 1000, "reason": "stop"}
    # One moment per window end time, both sensors where both have a window, one-to-one; all sent by the stop.
    moments = [m for m in messages if m["type"] == "moment"]
    assert [m["window_end_s"] for m in moments] == [round((127 + 16 * k) / 60, 6) for k in range(3)]
    assert [sorted(m["segments"]) for m in moments] == [["a", "b"], ["a", "b"], ["a"]]
    for m in moments[:2]:
        both = list(m["segments"].values())
        assert None in both or both[0] != both[1]
    kinds = [m["type"] for m in messages]
    assert len(kinds) - kinds[::-1].index("moment") < len(kinds) - kinds[::-1].index("assignment")  # moments first


def test_a_sensor_that_never_sends_holds_up_moments_for_32_windows_only(client: TestClient) -> None:
    n = 128 + 16 * 40  # 41 windows of sensor a; sensor b sends nothing
    with client.websocket_connect("/v1/stream") as ws:
        ws.send_text(json.dumps(START))
        ws.receive_text()
        ws.send_bytes(encode_binary(0, 0, _signal(n)))
        moments = []
        while len(moments) < 41 - 32:
            message = json.loads(ws.receive_text())
            if message["type"] == "moment":
                moments.append(message)
        assert all(m["segments"].keys() == {"a"} for m in moments)  # answered without b before the stop
        ws.send_text(json.dumps({"type": "stop"}))
        rest = [m for m in _collect(ws) if m["type"] == "moment"]
    assert len(moments) + len(rest) == 41


def test_gaps_and_late_packets_are_reported(client: TestClient) -> None:
    x = _signal(64)
    with client.websocket_connect("/v1/stream") as ws:
        ws.send_text(json.dumps(START))
        ws.receive_text()
        ws.send_bytes(encode_binary(0, 0, x[:32]))
        ws.send_bytes(encode_binary(0, 40, x[:16]))
        ws.send_bytes(encode_binary(0, 10, x[:4]))
        ws.send_text(json.dumps({"type": "stop"}))
        messages = _collect(ws)
    gap = next(m for m in messages if m["type"] == "gap")
    assert (gap["expected_seq"], gap["received_seq"], gap["missing"]) == (32, 40, 8)
    late = next(m for m in messages if m["type"] == "late")
    assert late["received_seq"] == 10 and late["action"] == "packet dropped"


@pytest.mark.parametrize(
    "first, then, code, fragment",
    [
        ("not json", None, 1003, "JSON"),
        (json.dumps({"type": "start", "sensors": []}), None, 1008, "sensors"),
        (json.dumps({"type": "start", "sensors": [{"sensor_id": "a", "acc_unit": "furlong"}]}), None, 1008, "acc_unit"),
        (
            json.dumps(START),
            json.dumps({"type": "samples", "sensor_id": "zz", "seq": 0, "samples": [[0] * 6]}),
            1008,
            "unknown sensor_id",
        ),
        (
            json.dumps(START),
            json.dumps({"type": "samples", "sensor_id": "a", "seq": 0, "samples": [[0] * 5]}),
            1008,
            "6 values",
        ),
        (
            json.dumps(START),
            '{"type": "samples", "sensor_id": "a", "seq": 0, "samples": [[NaN, 0, 0, 0, 0, 0]]}',
            1008,
            "finite",
        ),
        (json.dumps(START | {"worn_segments": ["LeftFoot", "LeftFoot"]}), None, 1008, "name each segment once"),
        (json.dumps(START | {"worn_segments": ["LeftHand"]}), None, 1008, "worn_segments.0"),
        (json.dumps(START | {"worn_segments": []}), None, 1008, "worn_segments"),
        (
            json.dumps(
                START
                | {"sensors": [{"sensor_id": "a", "candidate_segments": ["Pelvis"]}], "worn_segments": ["LeftFoot"]}
            ),
            None,
            1008,
            "invalid start message: sensors[0].candidate_segments: none of ['Pelvis'] is among worn_segments",
        ),
        (
            json.dumps({"type": "start", "sensors": [{"sensor_id": "a", "candidate_segments": ["Hip"]}]}),
            None,
            1008,
            "candidate_segments.0",
        ),
        (json.dumps(START), b"\x00\x00", 1003, "header"),
        (json.dumps(START), encode_binary(7, 0, np.zeros((1, 6))), 1008, "sensor index 7"),
        (json.dumps(START), encode_binary(0, 0, np.zeros((5000, 6))), 1009, "at most"),
    ],
)
def test_protocol_violations_close_with_code_and_message(client: TestClient, first, then, code, fragment) -> None:
    with client.websocket_connect("/v1/stream") as ws:
        ws.send_text(first)
        if then is not None:
            ws.receive_text()  # started
            ws.send_bytes(then) if isinstance(then, bytes) else ws.send_text(then)
        messages = _collect(ws)
    error = next(m for m in messages if m["type"] == "error")
    assert fragment in error["detail"] and error["close_code"] == code
    assert messages[-1]["code"] == code
    # the server keeps serving others
    assert client.get("/health").status_code == 200


def _window_ends(messages: list[dict]) -> list[float]:
    return [m["window_end_s"] for m in messages if m["type"] == "result"]


def _metric(client: TestClient, name: str) -> float:
    line = next(x for x in client.get("/metrics").text.splitlines() if x.startswith(name + " "))
    return float(line.split()[-1])


def _stream_one_sensor(ws, x: np.ndarray, stop: bool = True) -> None:  # type: ignore[no-untyped-def]
    """Start a session with sensor "a", send ``x`` as 16-sample binary packets, then (optionally) stop."""
    ws.send_text(json.dumps({"type": "start", "sensors": [{"sensor_id": "a"}]}))
    ws.receive_text()
    for seq in range(0, len(x), 16):
        ws.send_bytes(encode_binary(0, seq, x[seq : seq + 16]))
    if stop:
        ws.send_text(json.dumps({"type": "stop"}))


def test_a_sensor_declared_on_one_segment_gets_it_at_every_moment(client: TestClient) -> None:
    """A one-sensor session whose sensor may only be the pelvis: ``started`` echoes the declaration, every moving
    moment answers Pelvis, every window's alignment is given for the pelvis (its class stays its own answer), and
    the joint answer is the pelvis with a null margin (JSON has no infinity)."""
    x = _signal(16 * 12)
    start = {"type": "start", "sensors": [{"sensor_id": "a", "candidate_segments": ["Pelvis"]}]}
    with client.websocket_connect("/v1/stream") as ws:
        ws.send_text(json.dumps(start))
        started = json.loads(ws.receive_text())
        for seq in range(0, len(x), 16):
            ws.send_bytes(encode_binary(0, seq, x[seq : seq + 16]))
        ws.send_text(json.dumps({"type": "stop"}))
        messages = _collect(ws)
    assert started["candidate_segments"] == {"a": ["Pelvis"]} and started["worn_segments"] is None
    moments = [m for m in messages if m["type"] == "moment"]
    assert len(moments) == 12 - 7 and {m["segments"]["a"] for m in moments} == {"Pelvis"}
    results = [m for m in messages if m["type"] == "result"]
    assert len(results) == 12 - 7 and {r["alignment"]["segment"] for r in results} == {"Pelvis"}
    final = [m for m in messages if m["type"] == "assignment"][-1]["sensors"][0]
    assert final["segment"] == "Pelvis" and final["margin"] is None and final["alignment"]["segment"] == "Pelvis"


def test_a_burst_of_packets_is_answered_in_order_with_few_inference_calls(client: TestClient) -> None:
    """A client that sends faster than real time (or fell behind) is not served one packet per model call:
    everything its socket holds goes through inference together, and the results keep their order."""
    x = _signal(16 * 64)
    calls_before = _metric(client, "wearmocap_inference_batch_windows_count")
    with client.websocket_connect("/v1/stream") as ws:
        _stream_one_sensor(ws, x)
        messages = _collect(ws)
    ends = _window_ends(messages)
    assert len(ends) == 64 - 7  # one window per 16 samples once 128 are buffered
    assert ends == sorted(ends) and len(set(ends)) == len(ends)
    assert _metric(client, "wearmocap_inference_batch_windows_count") - calls_before < len(ends)
    assert messages[-1]["code"] == 1000
    assert "moment" not in {m["type"] for m in messages}  # one sensor: its moments are its results


def test_pending_window_limit_slows_reading_but_loses_nothing(tiny_models) -> None:
    settings = Settings(models_dir=tiny_models, stream_max_pending_windows=1)
    x = _signal(16 * 20)
    with TestClient(create_app(settings)) as c, c.websocket_connect("/v1/stream") as ws:
        _stream_one_sensor(ws, x)
        messages = _collect(ws)
    assert len(_window_ends(messages)) == 20 - 7
    assert messages[-1]["code"] == 1000


def test_results_of_accepted_packets_precede_the_error_close(client: TestClient) -> None:
    x = _signal(16 * 12)
    with client.websocket_connect("/v1/stream") as ws:
        _stream_one_sensor(ws, x, stop=False)
        ws.send_bytes(encode_binary(3, len(x), x[:16]))  # sensor index 3 was never declared
        messages = _collect(ws)
    kinds = [m["type"] for m in messages]
    assert kinds.count("result") == 12 - 7
    assert kinds.index("error") > max(i for i, k in enumerate(kinds) if k == "result")
    assert messages[-1]["code"] == 1008


def test_a_lone_surrogate_in_a_message_is_reported_not_crashed_on(client: TestClient) -> None:
    with client.websocket_connect("/v1/stream") as ws:
        ws.send_text(json.dumps({"type": "start", "sensors": [{"sensor_id": "a"}]}))
        ws.receive_text()
        ws.send_text('{"type": "samples", "sensor_id": "\\ud800", "seq": 0, "samples": [[0, 0, 9.8, 0, 0, 0]]}')
        messages = _collect(ws)
    error = next(m for m in messages if m["type"] == "error")
    assert "unknown sensor_id" in error["detail"]
    assert messages[-1]["code"] == 1008


def test_a_sensor_whose_readings_do_not_fit_its_declared_units_gets_one_warning(client: TestClient) -> None:
    """As the REST routes' ``warnings``: sensor a sends g while declaring m/s² and is warned once, after its first
    four windows; sensor b, in the declared unit, is not; nothing stops the stream."""
    n = 128 + 16 * 8
    x = _signal(n)
    with client.websocket_connect("/v1/stream") as ws:
        ws.send_text(json.dumps({"type": "start", "sensors": [{"sensor_id": "a"}, {"sensor_id": "b"}]}))
        ws.receive_text()
        for seq in range(0, n, 16):
            ws.send_bytes(encode_binary(0, seq, x[seq : seq + 16] / 9.80665))  # g, declared as m/s²
            ws.send_bytes(encode_binary(1, seq, x[seq : seq + 16]))
        ws.send_text(json.dumps({"type": "stop"}))
        messages = _collect(ws)
    warnings = [m for m in messages if m["type"] == "warning"]
    assert [w["sensor_id"] for w in warnings] == ["a"]
    [text] = warnings[0]["warnings"]
    assert text.startswith("acc_unit:") and "'g'" in text
    a_results = [m for m in messages if m["type"] == "result" and m["sensor_id"] == "a"]
    assert len(a_results) == 9 and messages[-1]["code"] == 1000  # every window answered, the stream went on
    assert messages.index(warnings[0]) > messages.index(a_results[3])  # after the four windows it reads


def test_a_sensor_that_has_not_moved_yet_is_answered_as_the_rest_route_answers_it(client: TestClient) -> None:
    """A sensor whose windows are all still (a pelvis on a slow walker, the first seconds) is weighed by its still
    windows, as ``/v1/imu/assign`` weighs it, not left out: the stream's running answer is the REST answer of the
    same windows, segment for segment, also for the still sensor."""
    still = np.zeros((160, 6))
    still[:, 2] = 9.81
    still[:, 3:] = np.random.default_rng(2).normal(scale=0.001, size=(160, 3))
    moving = _signal(160, 3)
    start = {"type": "start", "sensors": [{"sensor_id": "still"}, {"sensor_id": "moving"}]}
    with client.websocket_connect("/v1/stream") as ws:
        ws.send_text(json.dumps(start))
        assert json.loads(ws.receive_text())["type"] == "started"
        ws.send_bytes(encode_binary(0, 0, still.astype(np.float32)))
        ws.send_bytes(encode_binary(1, 0, moving.astype(np.float32)))
        ws.send_text(json.dumps({"type": "stop"}))
        messages = _collect(ws)
    results = [m for m in messages if m["type"] == "result"]
    assert not any(r["moving"] for r in results if r["sensor_id"] == "still")
    assert all(r["moving"] for r in results if r["sensor_id"] == "moving")
    final = {s["sensor_id"]: s for s in [m for m in messages if m["type"] == "assignment"][-1]["sensors"]}
    windows = {
        name: [x[k : k + 128].tolist() for k in (0, 16, 32)] for name, x in (("still", still), ("moving", moving))
    }
    body = {"sensors": [{"sensor_id": n, "windows": [{"samples": w} for w in ws_]} for n, ws_ in windows.items()]}
    rest = {s["sensor_id"]: s for s in client.post("/v1/imu/assign", json=body).json()["sensors"]}
    assert final["still"]["segment"] is not None and final["still"]["windows"] == 0
    for name in ("still", "moving"):
        assert final[name]["segment"] == rest[name]["segment"]
        assert final[name]["confidence"] == pytest.approx(rest[name]["confidence"], abs=1e-4)


def _start_one_sensor(ws) -> dict:
    ws.send_text(json.dumps({"type": "start", "sensors": [{"sensor_id": "a"}]}))
    started = json.loads(ws.receive_text())
    assert started["type"] == "started"
    return started


def _hop_by_hop(ws, x: np.ndarray) -> list[dict]:
    """Send ``x`` one 16-sample hop at a time, each hop's result read before the next is sent."""
    messages = []
    for seq in range(0, len(x), 16):
        ws.send_bytes(encode_binary(0, seq, x[seq : seq + 16]))
        if seq + 16 >= 128:  # a window ends in this hop: wait for its result
            while (m := json.loads(ws.receive_text()))["type"] != "result":
                messages.append(m)
            messages.append(m)
    return messages


@pytest.mark.parametrize(
    ("interval_s", "expected_windows"), [(0.5, [1, 3, 5, 7, 8]), (0.0, [1, 2, 3, 4, 5, 6, 7, 8, 8])]
)
def test_the_running_assignment_goes_out_once_per_interval_of_stream_time(
    tiny_models, interval_s: float, expected_windows: list[int]
) -> None:
    """A sensor streamed hop by hop (a window every 16 samples at 60 Hz, 0.27 s of stream time) gets an assignment
    message after its first result, then after every second one (the windows it makes in 0.5 s), and one at stop
    over every window; with 0, one after every group of results."""
    x = _signal(128 + 16 * 7)
    settings = Settings(models_dir=tiny_models, stream_assignment_interval_s=interval_s)
    with TestClient(create_app(settings)) as c, c.websocket_connect("/v1/stream") as ws:
        assert _start_one_sensor(ws)["assignment_interval_s"] == interval_s
        messages = _hop_by_hop(ws, x)
        ws.send_text(json.dumps({"type": "stop"}))
        messages += _collect(ws)
    assert sum(m["type"] == "result" for m in messages) == 8
    windows = [m["sensors"][0]["windows"] for m in messages if m["type"] == "assignment"]
    assert windows == expected_windows


def test_the_last_assignment_reads_every_window_as_the_rest_route_does(client: TestClient) -> None:
    """52 windows hop by hop: the running alignment mean is refreshed by sixteenths, but the message at stop is
    /v1/imu/assign's robust mean over all 52 windows."""
    x = _signal(128 + 16 * 51, seed=3)
    with client.websocket_connect("/v1/stream") as ws:
        _start_one_sensor(ws)
        messages = _hop_by_hop(ws, x)
        ws.send_text(json.dumps({"type": "stop"}))
        messages += _collect(ws)
    results = [m for m in messages if m["type"] == "result"]
    assert len(results) == 52 and all(r["moving"] for r in results)
    final = [m for m in messages if m["type"] == "assignment"][-1]["sensors"][0]
    assert final["windows"] == 52
    windows = [{"samples": x[16 * k : 16 * k + 128].tolist()} for k in range(52)]
    want = client.post("/v1/imu/assign", json={"sensors": [{"sensor_id": "a", "windows": windows}]}).json()
    want = want["sensors"][0]
    assert final["segment"] == want["segment"] == final["alignment"]["segment"]
    np.testing.assert_allclose(final["alignment"]["q_segment_imu"], want["alignment"]["q_segment_imu"], atol=1e-5)
    assert final["alignment_spread_deg"] == pytest.approx(want["alignment_spread_deg"], abs=0.01)  # float32 batches


def test_a_session_that_ends_in_an_error_gets_the_assignment_over_all_its_results_first(client: TestClient) -> None:
    x = _signal(128 + 16 * 7)
    with client.websocket_connect("/v1/stream") as ws:
        _start_one_sensor(ws)
        messages = _hop_by_hop(ws, x)
        ws.send_text(json.dumps({"type": "bogus"}))
        messages += _collect(ws)
    kinds = [m["type"] for m in messages]
    assert kinds[-3:] == ["assignment", "error", "close"] and messages[-1]["code"] == 1008
    assert [m["sensors"][0]["windows"] for m in messages if m["type"] == "assignment"] == [1, 3, 5, 7, 8]
