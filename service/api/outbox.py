"""What a WebSocket session sends, bounded whatever the client does: the outgoing queue, its sender, the
slow-consumer watchdog, and the close.

Every outgoing message type is bounded:

- ``result``, ``moment``, ``pose``, ``angles``: at most ``limit`` queued; when full, the oldest of them is
  dropped, counted in ``wearmocap_stream_results_dropped_total`` and reported in the next assignment message
  (``results_dropped``);
- ``assignment``: only the newest matters, so a new one replaces the one still queued (and takes its place at
  the end of the queue);
- ``gap`` and ``late``: a new notice for a sensor whose notice of that type is still queued is merged into it
  (``count`` notices, ``missing`` summed, the latest sequence numbers), never queued one by one;
- ``started``, ``error``: once each per session; ``calibration``: at most one per still span of frames received
  (still-pose sessions) or per ``calibrate`` message, and once when the assignment hands over.

Queued messages are held encoded (a string of a few hundred bytes each, or the bytes of a binary pose block; not
a tree of Python objects).

A consumer that stays behind is closed with 1008 and a reason (``watch``): when no message has left for
``slow_s`` seconds while messages wait (its socket's buffers are full: it does not read), or when results have been
dropped for it without pause for ``slow_s`` seconds. The close frame goes out behind what the client has not read
yet, so a client that reads again learns why.
"""

from __future__ import annotations

import asyncio
import json
import logging
import time
from collections import deque
from collections.abc import Coroutine
from typing import Any

import orjson
from fastapi import WebSocket, WebSocketDisconnect
from starlette.websockets import WebSocketState

from service.api.guard import key_subprotocol, websocket_refusal

log = logging.getLogger(__name__)
DROPPABLE = ("result", "moment", "pose", "angles")
MERGED = ("gap", "late")


def encode(message: dict) -> str:
    try:
        return orjson.dumps(message, option=orjson.OPT_SERIALIZE_NUMPY).decode()
    except orjson.JSONEncodeError:  # an error detail echoing a lone surrogate that the client sent ("\\ud800")
        return json.dumps(message, ensure_ascii=True)


class Outbox:
    """Bounded outgoing queue of one WebSocket session (see the module docstring)."""

    def __init__(self, limit: int) -> None:
        self.items: deque[tuple[str, object]] = deque()  # (type, encoded text) or (type, key of a live message)
        self.live: dict[object, dict] = {}  # assignment and gap/late messages still open for replacement or merging
        self.limit = limit
        self.droppable = 0
        self.event = asyncio.Event()
        self.dropped = 0
        self.sending = False  # a message is taken off the queue and not yet handed to the socket
        self.last_sent = time.monotonic()  # when a message last left (or the queue last became non-empty)
        self.dropping_since: float | None = None

    def put(self, message: dict) -> bool:
        """Queue ``message``; True if a result had to be dropped for it."""
        kind = message["type"]
        if not self.items and not self.sending:
            self.last_sent = time.monotonic()
        if kind == "assignment" or kind in MERGED:
            return self._put_live(kind, message)
        return self._append(kind, encode(message))

    def put_binary(self, kind: str, data: bytes) -> bool:
        """Queue a binary message of a droppable ``kind`` (a binary pose block); True if a result was dropped."""
        if not self.items and not self.sending:
            self.last_sent = time.monotonic()
        return self._append(kind, data)

    def _append(self, kind: str, item: str | bytes) -> bool:
        dropped = False
        if kind in DROPPABLE:
            if self.droppable >= self.limit:
                dropped = self._drop_oldest()
            self.droppable += 1
        self.items.append((kind, item))
        self.event.set()
        return dropped

    def _put_live(self, kind: str, message: dict) -> bool:
        key = (kind, message.get("sensor_id"))
        queued = self.live.get(key)
        if queued is None:
            self.live[key] = message if kind == "assignment" else {**message, "count": 1}
            self.items.append((kind, key))
            self.event.set()
        elif kind == "assignment":  # the newest replaces the queued one, and goes out after the results before it
            self.items.remove((kind, key))
            self.items.append((kind, key))
            self.live[key] = message
        else:
            queued["count"] += 1
            for field in ("received_seq", "seq", "action", "detail"):
                if field in message:
                    queued[field] = message[field]
            for field in ("missing", "samples_dropped"):
                if field in message:
                    queued[field] = queued.get(field, 0) + message[field]
        return False

    def _drop_oldest(self) -> bool:
        for k, (kind, _) in enumerate(self.items):
            if kind in DROPPABLE:
                del self.items[k]
                self.droppable -= 1
                self.dropped += 1
                if self.dropping_since is None:
                    self.dropping_since = time.monotonic()
                return True
        return False

    def pop(self) -> str | bytes:
        kind, item = self.items.popleft()
        if kind in DROPPABLE:
            self.droppable -= 1
            if self.droppable < self.limit // 2:
                self.dropping_since = None
        if isinstance(item, (str, bytes)):
            return item
        message = self.live.pop(item)
        if kind == "assignment":
            message = {**message, "results_dropped": self.dropped}
        return encode(message)

    def stalled(self, slow_s: float, now: float | None = None) -> str | None:
        """Why the consumer counts as staying behind, or None."""
        now = time.monotonic() if now is None else now
        waiting = len(self.items) + self.sending
        if waiting and now - self.last_sent > slow_s:
            return f"consumer too slow: no message taken for {now - self.last_sent:.0f} s while {waiting} wait"
        if self.dropping_since is not None and now - self.dropping_since > slow_s:
            return f"consumer too slow: results dropped for {now - self.dropping_since:.0f} s ({self.dropped} in all)"
        return None


async def sender(ws: WebSocket, outbox: Outbox) -> None:
    while True:
        await outbox.event.wait()
        outbox.event.clear()
        while outbox.items:
            outbox.sending = True
            try:
                item = outbox.pop()
                await (ws.send_bytes(item) if isinstance(item, bytes) else ws.send_text(item))
                outbox.last_sent = time.monotonic()
            except (WebSocketDisconnect, RuntimeError, OSError):  # the client left or was closed; the receive loop
                return  # sees it and ends the session
            finally:
                outbox.sending = False


async def watch(outbox: Outbox, slow_s: float) -> str:
    """Returns (the reason) once the consumer has stayed behind; runs beside the session's receive loop."""
    while True:
        await asyncio.sleep(min(1.0, slow_s / 4))
        reason = outbox.stalled(slow_s)
        if reason is not None:
            return reason


async def accept(ws: WebSocket) -> bool:
    """Accept the handshake; a refused one (key, origin) is then closed with 1008 and the reason (a bare HTTP 403
    could not carry it). False if refused."""
    await ws.accept(subprotocol=key_subprotocol(ws.headers))  # a browser drops a socket that does not echo it
    why = websocket_refusal(ws.app.state.settings, ws.headers)
    if why is None:
        return True
    ws.app.state.metrics.streams_refused.labels("key" if "X-API-Key" in why else "origin").inc()
    await ws.send_text(json.dumps({"type": "error", "detail": why, "close_code": 1008}))
    await close(ws, 1008, why)
    return False


async def serve_watched(serving: Coroutine[Any, Any, None], outbox: Outbox, slow_s: float) -> None:
    """Run a session's receive loop beside the slow-consumer watchdog; ``SlowConsumer`` if the watchdog fires."""
    loop_task, watch_task = asyncio.ensure_future(serving), asyncio.ensure_future(watch(outbox, slow_s))
    try:
        await asyncio.wait((loop_task, watch_task), return_when=asyncio.FIRST_COMPLETED)
    finally:
        for task in (loop_task, watch_task):
            if not task.done():
                task.cancel()
    if loop_task.done() and not loop_task.cancelled():
        return loop_task.result()
    raise SlowConsumer(watch_task.result())


class SlowConsumer(Exception):
    """The client stays behind: the session is closed with 1008 and this reason."""


async def close_slow(ws: WebSocket, outbox: Outbox, sender_task: asyncio.Task, reason: str) -> None:
    """Drop what the client will not read, then close with 1008 and the reason (it waits in the socket behind
    what the client has not read yet)."""
    sender_task.cancel()
    outbox.items.clear()
    outbox.live.clear()
    ws.app.state.metrics.streams_closed.labels("1008-slow").inc()
    await close(ws, 1008, reason)


async def end_session(ws: WebSocket, outbox: Outbox, sender_task: asyncio.Task, code: int, reason: str) -> None:
    """The one way a session ends: a slow consumer is cut short with its reason; a session closed by the service
    (stop, protocol error, refusal) first sends what is queued, then the close; a client that left (``code`` -1,
    ``reason`` says why) has nobody to tell. Counted in ``wearmocap_streams_closed_total``."""
    metrics = ws.app.state.metrics
    if code == 1008 and reason.startswith("consumer too slow"):
        await close_slow(ws, outbox, sender_task, reason)
    elif code != -1:
        metrics.streams_closed.labels(str(code)).inc()
        await drain(outbox, sender_task)
        await close(ws, code, reason)
    else:
        metrics.streams_closed.labels(reason).inc()
        sender_task.cancel()


async def close(ws: WebSocket, code: int, reason: str) -> None:
    """Close with ``code``, unless the client has gone already (then there is nobody to tell)."""
    if WebSocketState.DISCONNECTED in (ws.application_state, ws.client_state):
        return
    try:
        await ws.close(code=code, reason=reason.encode(errors="replace")[:120].decode(errors="ignore"))
    except (WebSocketDisconnect, RuntimeError, OSError):  # the client left, or the server closed it, meanwhile
        log.debug("stream client left before the close frame")


async def drain(outbox: Outbox, task: asyncio.Task, timeout_s: float = 5.0) -> None:
    """Let the sender flush what is queued (bounded), then stop it."""
    deadline = asyncio.get_running_loop().time() + timeout_s
    while (outbox.items or outbox.sending) and asyncio.get_running_loop().time() < deadline and not task.done():
        await asyncio.sleep(0.005)
    task.cancel()
