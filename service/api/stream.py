"""WebSocket ``/v1/stream`` (protocol in ``service.api.protocol``).

A slow consumer never grows server memory without bound: outgoing messages go through a bounded
queue; when it is full the oldest queued *result* is dropped (assignment, gap and error messages are
kept), the drop is counted in ``wearmocap_stream_results_dropped_total`` and reported to the client
in the next assignment message as ``results_dropped``.
"""

from __future__ import annotations

import asyncio
import json
import logging
import time
from collections import deque

import numpy as np
from fastapi import APIRouter, WebSocket, WebSocketDisconnect
from pydantic import ValidationError
from starlette.websockets import WebSocketState

from service.api.protocol import (
    ProtocolError,
    SamplesMessage,
    StartMessage,
    check_samples,
    decode_binary,
)
from service.core.assignment import is_moving, joint_assignment
from service.core.segments import SEGMENTS
from service.core.stream import SensorStream
from service.inference.predict import window_results

log = logging.getLogger(__name__)
router = APIRouter()


class Outbox:
    """Bounded outgoing queue; drops the oldest result when full."""

    def __init__(self, limit: int) -> None:
        self.items: deque[dict] = deque()
        self.limit = limit
        self.event = asyncio.Event()
        self.dropped = 0

    def put(self, message: dict) -> bool:
        dropped = False
        if len(self.items) >= self.limit:
            for k, item in enumerate(self.items):
                if item["type"] == "result":
                    del self.items[k]
                    self.dropped += 1
                    dropped = True
                    break
        self.items.append(message)
        self.event.set()
        return dropped


async def _sender(ws: WebSocket, outbox: Outbox) -> None:
    while True:
        await outbox.event.wait()
        outbox.event.clear()
        while outbox.items:
            try:
                await ws.send_text(json.dumps(outbox.items.popleft()))
            except WebSocketDisconnect:  # the client left; the receive loop sees it and ends the session
                return


class Session:
    def __init__(self, start: StartMessage) -> None:
        ids = [s.sensor_id for s in start.sensors]
        if len(set(ids)) != len(ids):
            raise ProtocolError(f"sensor_id values must be unique, got {ids}")
        self.streams = [SensorStream(s.sensor_id, s.sample_rate_hz, s.acc_unit, s.gyr_unit) for s in start.sensors]
        self.index = {s.sensor_id: k for k, s in enumerate(self.streams)}
        self.allow_shared = start.allow_shared
        self.evidence = np.zeros((len(self.streams), len(SEGMENTS)))
        self.windows = np.zeros(len(self.streams), dtype=np.int64)

    def assignment_message(self, dropped: int) -> dict:
        joint = joint_assignment([e[None] for e in self.evidence], allow_shared=self.allow_shared)
        sensors = [
            {
                "sensor_id": s.sensor_id,
                "segment": SEGMENTS[g] if g >= 0 and n else None,
                "confidence": float(c) if n else 0.0,
                "margin": float(m) if n else 0.0,
                "windows": int(n),
            }
            for s, g, c, m, n in zip(
                self.streams, joint.segment, joint.confidence, joint.margin, self.windows, strict=True
            )
        ]
        return {"type": "assignment", "sensors": sensors, "results_dropped": dropped}


async def _handle_packet(
    ws: WebSocket, session: Session, k: int, seq: int, samples: np.ndarray, outbox: Outbox
) -> None:
    app = ws.app
    received = time.perf_counter()
    stream = session.streams[k]
    pushed = stream.push(seq, samples)
    app.state.metrics.samples.inc(len(samples))
    for kind, problem, extra in (("gap", pushed.gap, "missing"), ("late", pushed.late, "action")):
        if problem is None:
            continue
        app.state.metrics.gaps.inc()
        expected, received = problem
        message = {"type": kind, "sensor_id": stream.sensor_id, "expected_seq": expected, "received_seq": received}
        message[extra] = received - expected if kind == "gap" else "packet dropped"
        outbox.put(message)
    if not pushed.windows:
        return
    imu = np.stack(pushed.windows)
    probs, quats = await app.state.batcher.infer(imu, app.state.settings.stream_batch_wait_ms)
    moving = is_moving(imu)
    for i, result in enumerate(window_results(probs, quats, moving)):
        message = {"type": "result", "sensor_id": stream.sensor_id, "window_end_s": round(pushed.window_end_s[i], 6)}
        message.update(result)
        if moving[i]:
            session.evidence[k] += np.log(np.clip(probs[i], 1e-12, 1.0))
            session.windows[k] += 1
        if outbox.put(message):
            app.state.metrics.dropped.inc()
    outbox.put(session.assignment_message(outbox.dropped))
    app.state.metrics.stream_result.observe(time.perf_counter() - received)


def _parse_text(text: str) -> dict:
    try:
        message = json.loads(text)
    except json.JSONDecodeError as exc:
        raise ProtocolError(f"messages must be JSON objects; could not parse: {exc.msg} at {exc.pos}", 1003) from None
    if not isinstance(message, dict) or "type" not in message:
        raise ProtocolError(f"messages need a 'type' field; got {str(message)[:80]}")
    return message


async def _receive_start(ws: WebSocket) -> Session:
    first = await ws.receive()
    if first.get("text") is None:
        raise ProtocolError("the first message must be a JSON 'start' message, got binary data", 1003)
    try:
        return Session(StartMessage.model_validate(_parse_text(first["text"])))
    except ValidationError as exc:
        raise ProtocolError(f"invalid start message: {_first_error(exc)}") from None


def _first_error(exc: ValidationError) -> str:
    err = exc.errors()[0]
    return f"{'.'.join(str(p) for p in err['loc'])}: {err['msg']}"


async def _serve(ws: WebSocket, session: Session, outbox: Outbox) -> None:
    settings = ws.app.state.settings
    max_samples = settings.stream_max_samples_per_packet
    while True:
        message = await ws.receive()
        if message["type"] == "websocket.disconnect":
            raise WebSocketDisconnect(message.get("code", 1000))
        if message.get("bytes") is not None:
            k, seq, samples = decode_binary(message["bytes"], len(session.streams), max_samples)
        else:
            data = _parse_text(message["text"])
            if data["type"] == "stop":
                outbox.put(session.assignment_message(outbox.dropped))
                return
            try:
                packet = SamplesMessage.model_validate(data)
            except ValidationError as exc:
                raise ProtocolError(f"invalid {data['type']!r} message: {_first_error(exc)}") from None
            if packet.sensor_id not in session.index:
                raise ProtocolError(f"unknown sensor_id {packet.sensor_id!r}; declared: {list(session.index)}")
            k, seq = session.index[packet.sensor_id], packet.seq
            if any(len(r) != 6 for r in packet.samples):
                raise ProtocolError(f"sensor {packet.sensor_id}: every sample needs 6 values")
            samples = np.asarray(packet.samples, dtype=np.float64)
        check_samples(samples, max_samples, f"sensor {session.streams[k].sensor_id}")
        await _handle_packet(ws, session, k, seq, samples, outbox)


@router.websocket("/v1/stream")
async def stream(ws: WebSocket) -> None:
    settings = ws.app.state.settings
    if settings.api_key and ws.headers.get("x-api-key") != settings.api_key:
        await ws.close(code=1008, reason="missing or wrong X-API-Key header")
        return
    await ws.accept()
    metrics = ws.app.state.metrics
    if "i2s_assignment" not in ws.app.state.models:
        await ws.send_text(json.dumps({"type": "error", "detail": "no i2s_assignment model is loaded"}))
        await ws.close(code=1011, reason="no model loaded")
        return
    outbox = Outbox(settings.stream_queue_limit)
    sender = asyncio.create_task(_sender(ws, outbox))
    metrics.open_streams.inc()
    code, reason = 1000, "stop"
    try:
        session = await _receive_start(ws)
        outbox.put(
            {
                "type": "started",
                "sensors": [s.sensor_id for s in session.streams],
                "window_samples": 128,
                "hop_samples": 16,
                "model_rate_hz": 60.0,
            }
        )
        await _serve(ws, session, outbox)
    except ProtocolError as exc:
        code, reason = exc.code, str(exc)
        outbox.put({"type": "error", "detail": reason, "close_code": code})
    except WebSocketDisconnect:
        code = -1
    finally:
        metrics.open_streams.dec()
        if code != -1:
            await _drain(outbox, sender)
            await _close(ws, code, reason)
        else:
            sender.cancel()


async def _close(ws: WebSocket, code: int, reason: str) -> None:
    """Close with ``code``, unless the client has gone already (then there is nobody to tell)."""
    if WebSocketState.DISCONNECTED in (ws.application_state, ws.client_state):
        return
    try:
        await ws.close(code=code, reason=reason.encode()[:120].decode(errors="ignore"))
    except (WebSocketDisconnect, RuntimeError):  # the client left while we were closing
        log.debug("stream client left before the close frame")


async def _drain(outbox: Outbox, sender: asyncio.Task, timeout_s: float = 5.0) -> None:
    """Let the sender flush what is queued (bounded), then stop it."""
    deadline = asyncio.get_running_loop().time() + timeout_s
    while outbox.items and asyncio.get_running_loop().time() < deadline and not sender.done():
        await asyncio.sleep(0.005)
    sender.cancel()
