"""WebSocket ``/v1/stream/flex``: joint angles from a live stream of flex-sensor or capacitive-sleeve readings.

Client → server
  {"type": "start", "model": "flex_bilstm_cm", "channels": ["LeftKnee_flex", ...], "sample_rate_hz": 20}
      (first message, once; ``model`` optional where one flex model is loaded; ``channels`` the declared order,
      which must be the model's; ``sample_rate_hz`` the model's rate or an integer multiple of it: each group of
      that many readings is averaged into one)
  {"type": "samples", "seq": 0, "samples": [[c0, c1, ...], ...]}      rows of the declared channels, oldest first
  binary packet (little-endian): uint16 0, uint16 n, uint32 seq, then n x C float32          8 + 4 C n bytes
  {"type": "stop"}
``seq`` counts readings at the stream's rate (the packet's first one); a packet that skips readings is a gap:
the calibration window starts again, and a "gap" message says so. Readings a packet repeats are "late" and
dropped; the packet's readings after them are kept.

Server → client
  started (model, version, channels, joints, joint_components, sample_rate_hz, window_samples, latency_samples,
  decimation) · angles ({"first_sample": i, "frames": n, "angles_deg": n x joints x components}: sample i at
  the model's rate is the first one answered; each answer is latency_samples behind the newest reading it saw;
  nothing comes until the first window of window_samples is full) · warning (once, over the first window's
  readings: every value small where the model takes counts, or a channel that never changes) · gap / late · error
  (then close, after the answers of every accepted packet).
Close codes: 1003 unsupported data, 1008 protocol violation (wrong channels, values out of range, NaN; a failed
read-out where the manifest declares ``flex.readout_check``, after the answers of the readings before it), 1009
message too big, 1011 no flex model loaded, 1013 at capacity (try again later), 1000 after stop; 1008 also for a
wrong key or origin and for a consumer that stays behind (``service.api.outbox``).
"""

from __future__ import annotations

import asyncio
import json
import logging
import time
from typing import Literal

import numpy as np
from fastapi import APIRouter, WebSocket, WebSocketDisconnect
from pydantic import BaseModel, ConfigDict, Field, ValidationError

from service.api.outbox import Outbox, SlowConsumer, accept, close, end_session, sender, serve_watched
from service.api.protocol import ProtocolError, decode_binary
from service.api.schemas import Sample
from service.api.stream import _first_error, _parse_text
from service.api.stream_admission import admit_or_refuse, record_answer_latency
from service.core.stream import repeated_samples
from service.inference.flex import FlexModel, LiveFlex, check_rows, readout_message
from service.inference.predict import InputError

log = logging.getLogger(__name__)
router = APIRouter()
MAX_DECIMATION = 20


class FlexStart(BaseModel):
    model_config = ConfigDict(extra="forbid")
    type: str = Field(pattern="^start$")
    model: str | None = Field(None, max_length=128)
    channels: list[str] = Field(min_length=1, max_length=64)
    sample_rate_hz: float | None = Field(
        None, gt=0.0, le=2000.0, allow_inf_nan=False, description="default: the model's rate"
    )


class FlexSamples(BaseModel):
    model_config = ConfigDict(extra="forbid")
    type: Literal["samples"]
    seq: int = Field(ge=0, strict=True)
    samples: list[Sample] = Field(min_length=1)


def _model_for(start: FlexStart, models: dict[str, FlexModel]) -> FlexModel:
    listing = {n: m.manifest.channels for n, m in sorted(models.items())}
    if start.model is not None:
        if start.model not in models:
            raise ProtocolError(f"model: no flex_pose model {start.model!r}; loaded: {listing}")
        model = models[start.model]
    else:
        fitting = [m for m in models.values() if m.manifest.channels == start.channels]
        if len(fitting) != 1:
            raise ProtocolError(f"model: name one of the loaded flex models {listing}")
        model = fitting[0]
    if start.channels != model.manifest.channels:
        raise ProtocolError(
            f"channels: {model.name} takes {model.manifest.channels} in this order, got {start.channels}"
        )
    return model


def _decimation(start: FlexStart, model: FlexModel) -> int:
    model_rate = model.manifest.sample_rate_hz
    rate = start.sample_rate_hz or model_rate
    factor = rate / model_rate
    if abs(factor - round(factor)) > 1e-6 or not 1 <= round(factor) <= MAX_DECIMATION:
        raise ProtocolError(
            f"sample_rate_hz: {model.name} runs at {model_rate:g} Hz; stream at that rate or an integer multiple of it "
            f"up to {MAX_DECIMATION}x, got {rate:g}"
        )
    return int(round(factor))


async def _receive_start(ws: WebSocket) -> tuple[LiveFlex, FlexStart]:
    first = await ws.receive()
    if first.get("text") is None:
        raise ProtocolError("the first message must be a JSON 'start' message, got binary data", 1003)
    try:
        start = FlexStart.model_validate(_parse_text(first["text"]))
    except ValidationError as exc:
        raise ProtocolError(f"invalid start message: {_first_error(exc)}") from None
    model = _model_for(start, ws.app.state.flex_models)
    return LiveFlex(model, _decimation(start, model)), start


def _started(live: LiveFlex) -> dict:
    m = live.model.manifest
    return {
        "type": "started",
        "model": m.name,
        "version": m.version,
        "channels": m.channels,
        "joints": m.joints,
        "joint_components": m.joint_components,
        "sample_rate_hz": m.sample_rate_hz,
        "window_samples": m.window_samples,
        "latency_samples": live.model.latency,
        "decimation": live.factor,
    }


async def _accept(ws: WebSocket, live: LiveFlex, seq: int, rows: np.ndarray, outbox: Outbox) -> None:
    received = time.perf_counter()
    try:
        check_rows(rows, live.model, f"packet seq {seq}: samples")
    except InputError as exc:
        raise ProtocolError(str(exc)) from None
    if seq < live.samples_in:
        dropped = repeated_samples(live.samples_in, seq, len(rows))
        outbox.put({"type": "late", "seq": seq, "expected_seq": live.samples_in, "samples_dropped": dropped})
        if dropped == len(rows):
            return
        seq, rows = live.samples_in, rows[dropped:]  # the part after the repeated readings is new: kept
    if seq > live.samples_in:
        outbox.put(
            {
                "type": "gap",
                "expected_seq": live.samples_in,
                "seq": seq,
                "missing": seq - live.samples_in,
                "detail": f"the calibration window starts again: answers resume after {live.model.window} samples",
            }
        )
        live.jump_to(seq)
    failure = None if live.readout is None else live.readout.first_failure(rows)
    if failure is not None:
        rows = rows[: failure.row]  # the readings before the failure are answered, then the stream closes
    if len(rows):
        if found := live.first_window_warnings(rows):
            outbox.put({"type": "warning", "warnings": found})
        await _answer(ws, live, rows, outbox, received)
    if failure is not None:
        where = f"reading {seq + failure.row} (packet seq {seq}, row {failure.row})"
        raise ProtocolError(readout_message(failure, live.model, where))


async def _answer(ws: WebSocket, live: LiveFlex, rows: np.ndarray, outbox: Outbox, received: float) -> None:
    first, angles = await ws.app.state.flex_batcher.submit(live, rows)
    if len(angles):
        message = {
            "type": "angles",
            "first_sample": int(first),
            "frames": len(angles),
            "angles_deg": np.round(angles.astype(np.float64), 3),
        }
        if outbox.put(message):
            ws.app.state.metrics.dropped.inc()
        record_answer_latency(ws.app, time.perf_counter() - received, flex=True)


async def _serve(ws: WebSocket, live: LiveFlex, outbox: Outbox) -> None:
    max_samples = ws.app.state.settings.stream_max_samples_per_packet
    width = len(live.model.manifest.channels)
    while True:
        message = await ws.receive()
        if message["type"] == "websocket.disconnect":
            raise WebSocketDisconnect(message.get("code", 1000))
        if message.get("bytes") is not None:
            _, seq, rows = decode_binary(message["bytes"], 1, max_samples, width)
            rows = rows.reshape(len(rows), width)  # a frame packet of the one sensor is its rows
        else:
            data = _parse_text(message["text"])
            if data["type"] == "stop":
                return
            if data["type"] != "samples":
                raise ProtocolError(
                    f"unexpected message type {str(data['type'])[:40]!r} in a started session: expected 'samples' "
                    "or 'stop'"
                )
            try:
                packet = FlexSamples.model_validate(data)
            except ValidationError as exc:
                raise ProtocolError(f"invalid {data['type']!r} message: {_first_error(exc)}") from None
            if len(packet.samples) > max_samples:
                raise ProtocolError(f"at most {max_samples} samples per packet, got {len(packet.samples)}", 1009)
            bad = next((len(r) for r in packet.samples if len(r) != width), None)
            if bad is not None:
                raise ProtocolError(
                    f"every sample needs {width} values ({', '.join(live.model.manifest.channels)}), got {bad}"
                )
            seq, rows = packet.seq, np.asarray(packet.samples, dtype=np.float64)
        await _accept(ws, live, seq, rows, outbox)


@router.websocket("/v1/stream/flex")
async def flex_stream(ws: WebSocket) -> None:
    if not await accept(ws):
        return
    if not ws.app.state.flex_models:
        await ws.send_text(json.dumps({"type": "error", "detail": "no flex_pose model is loaded"}))
        await close(ws, 1011, "no flex model loaded")
        return
    settings, metrics = ws.app.state.settings, ws.app.state.metrics
    outbox = Outbox(settings.stream_queue_limit)
    sending = asyncio.create_task(sender(ws, outbox))
    metrics.open_streams.inc()
    code, reason = 1000, "stop"
    admitted: int | None = None
    try:
        live, _ = await _receive_start(ws)
        admitted = _admit(ws, live)
        outbox.put(_started(live))
        await serve_watched(_serve(ws, live, outbox), outbox, settings.stream_slow_consumer_s)
    except ProtocolError as exc:
        code, reason = exc.code, str(exc)
        outbox.put({"type": "error", "detail": reason, "close_code": code})
    except SlowConsumer as exc:
        code, reason = 1008, str(exc)
    except WebSocketDisconnect as exc:
        code, reason = -1, "1008-slow" if exc.code == 1008 else "client"  # 1008: closed for not answering a ping
    except Exception:  # a fault of the service, not of the client: 1011, never a normal close
        log.exception("stream session failed")
        code, reason = 1011, "internal error: the session failed; what was answered before stands"
        outbox.put({"type": "error", "detail": reason, "close_code": code})
    finally:
        metrics.open_streams.dec()
        ws.app.state.streams.release(admitted)
        await end_session(ws, outbox, sending, code, reason)


def _admit(ws: WebSocket, live: LiveFlex) -> int:
    """The session's admission key; ProtocolError 1013 when the streams are at capacity."""
    app = ws.app
    why = app.state.streams.flex_refusal()
    if why:
        app.state.metrics.streams_refused.labels("capacity").inc()
        raise ProtocolError(why, 1013)
    rate = live.model.manifest.sample_rate_hz
    return admit_or_refuse(app, app.state.streams.model_demand(app.state.batcher, live.model.name, rate))
