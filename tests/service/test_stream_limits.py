"""Bounded streams: the outbox's bound for every message type, refused handshakes closed with a reason, admission
against the capacity, and a consumer that stops reading closed with 1008 and a reason by a real uvicorn server."""

from __future__ import annotations

import asyncio
import json
import socket
import time
from pathlib import Path

import httpx
import numpy as np
import pytest
import websockets
from fastapi.testclient import TestClient
from starlette.websockets import WebSocketDisconnect

from benchmarks.servers import start_service, stop
from service.api.outbox import Outbox
from service.api.protocol import encode_binary
from service.app import create_app
from service.settings import Settings


def _drain_all(outbox: Outbox) -> list[dict]:
    out = []
    while outbox.items:
        out.append(json.loads(outbox.pop()))
    return out


def test_every_message_type_is_bounded_in_the_outbox() -> None:
    outbox = Outbox(limit=8)
    for k in range(5000):
        outbox.put({"type": "late", "sensor_id": "a", "expected_seq": 100, "received_seq": k, "action": "dropped"})
        outbox.put({"type": "gap", "sensor_id": "a", "expected_seq": k, "received_seq": k + 3, "missing": 3})
        outbox.put({"type": "assignment", "sensors": [k], "results_dropped": 0})
        outbox.put({"type": "result", "sensor_id": "a", "k": k})
    assert len(outbox.items) == 8 + 3  # 8 results, one late, one gap, one assignment
    messages = _drain_all(outbox)
    late = next(m for m in messages if m["type"] == "late")
    gap = next(m for m in messages if m["type"] == "gap")
    assert late["count"] == 5000 and late["received_seq"] == 4999
    assert gap["count"] == 5000 and gap["missing"] == 15000
    assignment = next(m for m in messages if m["type"] == "assignment")
    assert assignment["sensors"] == [4999] and assignment["results_dropped"] == 4992
    assert [m["k"] for m in messages if m["type"] == "result"] == list(range(4992, 5000))
    assert messages[-1]["type"] == "result" and messages[-2]["type"] == "assignment"


def test_a_consumer_counts_as_staying_behind_when_nothing_leaves_or_results_keep_dropping() -> None:
    outbox = Outbox(limit=4)
    start = time.monotonic()
    outbox.put({"type": "result", "k": 0})
    assert outbox.stalled(5.0, start + 4.0) is None
    assert "no message taken for" in outbox.stalled(5.0, start + 6.0)
    outbox = Outbox(limit=4)
    for k in range(10):
        outbox.put({"type": "result", "k": k})
    outbox.pop()
    outbox.last_sent = time.monotonic() + 100  # messages do leave ...
    assert "results dropped for" in outbox.stalled(5.0, time.monotonic() + 6.0)  # ... but not fast enough


@pytest.mark.parametrize(
    ("settings", "headers", "fragment"),
    [
        ({"api_key": "s3cret"}, {}, "X-API-Key"),
        ({"api_key": "s3cret"}, {"X-API-Key": "s3crex"}, "X-API-Key"),
        ({"allowed_origins": "https://lab.example.org"}, {"Origin": "https://evil.example"}, "not allowed"),
    ],
)
def test_a_refused_handshake_is_closed_with_1008_and_the_reason(tiny_models: Path, settings, headers, fragment) -> None:
    with TestClient(create_app(Settings(models_dir=tiny_models, **settings))) as c:
        for path in ("/v1/stream", "/v1/stream/flex"):
            with c.websocket_connect(path, headers=headers) as ws:
                error = json.loads(ws.receive_text())
                assert error["type"] == "error" and fragment in error["detail"]
                with pytest.raises(WebSocketDisconnect) as closed:
                    ws.receive_text()
                assert closed.value.code == 1008 and fragment in closed.value.reason
        assert "wearmocap_streams_refused_total{reason=" in c.get("/metrics", headers=headers).text


def test_streams_beyond_the_capacity_are_refused_with_1013(tiny_models: Path) -> None:
    # 10 windows/s, streams may take 80 %: two 60 Hz sensors (7.5 windows/s) fit, a third does not.
    settings = Settings(models_dir=tiny_models, capacity_windows_per_s=10.0, stream_capacity_fraction=0.8)
    start = {"type": "start", "sensors": [{"sensor_id": "a"}, {"sensor_id": "b"}]}
    with TestClient(create_app(settings)) as c:
        with c.websocket_connect("/v1/stream") as first:
            first.send_text(json.dumps(start))
            assert json.loads(first.receive_text())["type"] == "started"
            with c.websocket_connect("/v1/stream") as second:
                second.send_text(json.dumps({"type": "start", "sensors": [{"sensor_id": "c"}]}))
                error = json.loads(second.receive_text())
                assert error["close_code"] == 1013 and "at capacity" in error["detail"]
                with pytest.raises(WebSocketDisconnect) as closed:
                    second.receive_text()
                assert closed.value.code == 1013 and "try again later" in closed.value.reason
        # the first one has gone: room again
        with c.websocket_connect("/v1/stream") as third:
            third.send_text(json.dumps({"type": "start", "sensors": [{"sensor_id": "c"}]}))
            assert json.loads(third.receive_text())["type"] == "started"
        metrics = c.get("/metrics").text
        assert "wearmocap_streams_admitted_total 2.0" in metrics
        assert 'wearmocap_streams_refused_total{reason="capacity"} 1.0' in metrics


def test_a_consumer_that_stops_reading_is_closed_with_1008_and_a_reason(tiny_models: Path) -> None:
    server, base = start_service(tiny_models, stream_slow_consumer_s="1", stream_queue_limit="64")
    try:
        asyncio.run(_slow_consumer(base.replace("http", "ws") + "/v1/stream"))
    finally:
        stop(server)


async def _slow_consumer(url: str) -> None:
    host, port = url.split("//")[1].split("/")[0].split(":")
    sock = socket.socket()
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)  # a slow link: little room in flight
    sock.connect((host, int(port)))
    # No keepalive pings from this client: it stops reading, so it would never see the server's pong and would
    # close the connection itself (1011 "keepalive ping timeout") on a slow machine before reading the server's close.
    async with websockets.connect(url, sock=sock, max_queue=1, ping_interval=None) as ws:
        await ws.send(json.dumps({"type": "start", "sensors": [{"sensor_id": "a"}]}))
        rng = np.random.default_rng(0)
        seq, deadline = 0, time.monotonic() + 20
        try:
            while time.monotonic() < deadline:  # replay fast and never read: results pile up
                await asyncio.wait_for(ws.send(encode_binary(0, seq, rng.normal(size=(1024, 6)))), 3)
                seq += 1024
                await asyncio.sleep(0.01)
        except (websockets.ConnectionClosed, TimeoutError):  # the server has stopped reading this client
            pass
        messages = []
        with pytest.raises(websockets.ConnectionClosed) as closed:
            while True:  # now read: what was queued, then the close frame and its reason
                messages.append(json.loads(await asyncio.wait_for(ws.recv(), 10)))
    assert closed.value.rcvd is not None, "no close frame reached the client"
    assert closed.value.rcvd.code == 1008 and "consumer too slow" in closed.value.rcvd.reason
    assert messages and messages[0]["type"] == "started"


def test_a_consumer_that_stops_answering_pings_is_closed_with_1008_before_its_buffers_fill(tiny_models: Path) -> None:
    # Real time, little output: the kernel's buffers take it all, but the client, which reads nothing, answers no
    # ping either.
    server, base = start_service(tiny_models, ws_ping_interval_s="0.5", ws_ping_timeout_s="1")
    try:
        asyncio.run(_not_reading(base.replace("http", "ws") + "/v1/stream"))
    finally:
        stop(server)


async def _not_reading(url: str) -> None:
    async with websockets.connect(url, max_queue=1, ping_interval=None) as ws:
        await ws.send(json.dumps({"type": "start", "sensors": [{"sensor_id": "a"}]}))
        x = np.random.default_rng(0).normal(size=(16, 6))
        for seq in range(0, 60 * 5, 16):  # 5 s in real time, reading nothing; sending goes on working throughout
            await ws.send(encode_binary(0, seq, x))
            await asyncio.sleep(16 / 60)
        with pytest.raises(websockets.ConnectionClosed) as closed:  # now read: the backlog, then why it was closed
            while True:
                await asyncio.wait_for(ws.recv(), 5)
    assert closed.value.rcvd is not None and closed.value.rcvd.code == 1008
    assert "no answer to a ping" in closed.value.rcvd.reason


def test_streams_are_refused_while_the_admitted_ones_answer_late(tiny_models: Path) -> None:
    with TestClient(create_app(Settings(models_dir=tiny_models, stream_latency_target_ms=100.0))) as c:
        admission = c.app.state.streams
        start = {"type": "start", "sensors": [{"sensor_id": "a"}]}
        with c.websocket_connect("/v1/stream") as first:
            first.send_text(json.dumps(start))
            assert json.loads(first.receive_text())["type"] == "started"
            for _ in range(60):
                admission.observe_latency(0.02)
            for _ in range(10):
                admission.observe_latency(0.4)  # the slowest 1 % of the last 10 s: 400 ms
            with c.websocket_connect("/v1/stream") as ws:
                ws.send_text(json.dumps(start))
                error = json.loads(ws.receive_text())
                assert error["close_code"] == 1013 and "answers take 400 ms at p99" in error["detail"]
        # Once no stream is open, what was measured is over.
        with c.websocket_connect("/v1/stream") as ws:
            ws.send_text(json.dumps(start))
            assert json.loads(ws.receive_text())["type"] == "started"


def test_a_text_message_that_is_not_utf8_is_closed_with_1007_and_where(tiny_models: Path) -> None:
    """uvicorn closed it with 1007 and no reason, and logged two tracebacks (its close raised on a connection the
    WebSocket library was already closing); the client is told which byte, and the log has one line."""
    from websockets.frames import Frame, Opcode

    from benchmarks.servers import server_log

    server, base = start_service(tiny_models)

    async def send_bad_text() -> websockets.ConnectionClosed:
        async with websockets.connect(base.replace("http", "ws") + "/v1/stream", ping_interval=None) as ws:
            await ws.send(json.dumps({"type": "start", "sensors": [{"sensor_id": "a"}]}))
            assert json.loads(await ws.recv())["type"] == "started"
            ws.protocol.send_frame(Frame(Opcode.TEXT, b'{"type": "\xff\xfe"}'))
            ws.send_data()
            with pytest.raises(websockets.ConnectionClosed) as closed:
                while True:
                    await asyncio.wait_for(ws.recv(), 10)
            return closed.value

    try:
        closed = asyncio.run(send_bad_text())
        assert httpx.get(base + "/health").status_code == 200  # the service goes on
    finally:
        stop(server)
    assert closed.rcvd is not None and closed.rcvd.code == 1007
    assert closed.rcvd.reason == "a text message must be UTF-8 JSON; byte 10 is not UTF-8 (invalid start byte)"
    log = server_log(base).read_text()
    assert "closing a WebSocket client with 1007" in log and "Traceback" not in log
