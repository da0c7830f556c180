"""Pure ASGI middleware in front of every HTTP request: API key, body-size limit on the bytes received, early load
shedding, metrics.

- The key is compared in constant time (``hmac.compare_digest``) on ``/v1/*`` and, with
  ``WEARMOCAP_METRICS_REQUIRE_KEY``, on ``/metrics``. WebSockets check it themselves (``websocket_refusal``): a
  refused WebSocket is accepted and closed with 1008 and a reason, which a bare HTTP 403 cannot carry.
- The body limit counts the bytes actually received, chunked or not: reading stops at the limit with a 413, so a
  client cannot make the process hold more than ``max_body_bytes`` of one body. The body is read here, once, and
  handed on to the route.
- Load shedding: a POST to ``/v1/*`` whose estimated wait passes ``request_deadline_s`` gets a 503 with
  ``Retry-After`` before its body is read or parsed. Two estimates: the inference queue (windows ahead at the
  measured seconds per window, and the requests admitted before it whose bodies are still being read) must stay
  within the deadline; for small requests, the ones admitted and not yet answered times the seconds between answers
  measured while busy (``service.api.request_cost``: everything a request costs, parsing, inference and answering,
  not inference alone) must stay within ``COMPLETION_DEADLINE_SHARE`` of it. Admitted requests carry their
  deadline (``scope["state"]["start_by"]``) to the scheduler, which checks it again with the exact number of
  windows.

Plain ASGI rather than ``@app.middleware("http")``: that wrapper costs about a millisecond per request
(measured with ``benchmarks.bench_service``), a fifth of the single-window latency budget.
"""

from __future__ import annotations

import asyncio
import base64
import hmac
import time
from collections.abc import Awaitable, Callable, MutableMapping
from typing import Any

from starlette.datastructures import State

from service.api.errors import error_response
from service.api.metrics import ServiceMetrics
from service.api.request_cost import COMPLETION_DEADLINE_SHARE, PROBE, Completions
from service.inference.batcher import Overloaded
from service.settings import Settings

Scope = MutableMapping[str, Any]
Message = MutableMapping[str, Any]
Receive = Callable[[], Awaitable[Message]]
Send = Callable[[Message], Awaitable[None]]
ASGIApp = Callable[[Scope, Receive, Send], Awaitable[None]]
JSON_BYTES_PER_WINDOW = 6144  # for the estimate before parsing: 768 numbers of about 8 characters
BINARY_BYTES_PER_WINDOW = 3072  # 128 samples × 6 float32
SMALL_REQUEST_WINDOWS = 64  # requests up to this size are counted by ``Completions``; larger ones by their windows
MAX_PARSE_WAIT_S = 0.05  # an admitted request waits at most this long for a quiet turn before it is parsed
DRAIN_SECONDS, DRAIN_BYTES = 5.0, 1 << 30  # how much of an over-limit body is read and discarded after the 413


def key_matches(settings: Settings, sent: str | bytes | None) -> bool:
    """True when no key is set, or ``sent`` is the key (constant-time comparison)."""
    if not settings.api_key:
        return True
    if sent is None:
        return False
    given = sent if isinstance(sent, bytes) else sent.encode(errors="replace")
    return hmac.compare_digest(given, settings.api_key.encode())


def allowed_origins(settings: Settings) -> list[str]:
    return [o.strip() for o in settings.allowed_origins.split(",") if o.strip()]


KEY_SUBPROTOCOL = "wearmocap.key."  # + the key in unpadded base64url: how a browser, which sets no headers, sends it


def key_subprotocol(headers: MutableMapping[str, str] | Any) -> str | None:
    """The ``Sec-WebSocket-Protocol`` entry that carries a key (``wearmocap.key.<base64url>``), or None."""
    offered = [p.strip() for p in headers.get("sec-websocket-protocol", "").split(",")]
    return next((p for p in offered if p.startswith(KEY_SUBPROTOCOL)), None)


def _key_of_subprotocol(protocol: str | None) -> bytes | None:
    if protocol is None:
        return None
    encoded = protocol.removeprefix(KEY_SUBPROTOCOL)
    try:
        return base64.urlsafe_b64decode(encoded + "=" * (-len(encoded) % 4))
    except ValueError:
        return None


def websocket_refusal(settings: Settings, headers: MutableMapping[str, str] | Any) -> str | None:
    """Why a WebSocket handshake with these headers is refused (key, origin), or None. The key comes in the
    ``X-API-Key`` header or, from a browser, as the subprotocol ``wearmocap.key.<key in base64url>``."""
    sent = headers.get("x-api-key")
    if sent is None:
        sent = _key_of_subprotocol(key_subprotocol(headers))
    if not key_matches(settings, sent):
        return "missing or wrong X-API-Key header (or wearmocap.key. subprotocol)"
    origins = allowed_origins(settings)
    origin = headers.get("origin")
    if origins and origin is not None and origin not in origins:
        return f"origin {origin[:80]!r} is not allowed; allowed: {origins}"
    return None


class Guard:
    def __init__(self, app: ASGIApp, settings: Settings, metrics: ServiceMetrics, state: State) -> None:
        self.app, self.settings, self.metrics, self.state = app, settings, metrics, state
        self.arrivals = 0  # requests seen so far
        self.parse_turn_taken = False  # a request has started parsing in this turn of the event loop
        self.completions = Completions()

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        start = time.perf_counter()
        status = 500

        async def tracked(message: Message) -> None:
            nonlocal status
            if message["type"] == "http.response.start":
                status = message["status"]
            await send(message)

        try:
            await self._handle(scope, receive, tracked)
        finally:
            if (started_at := scope.get("state", {}).get("counted_since")) is not None:
                self.completions.ended(started_at, status < 400)
            if not scope.get("state", {}).get(PROBE):  # the start-up probe's requests are not clients' requests
                # The route template, not the raw path: label values stay bounded whatever clients send.
                route = scope.get("route")
                path = getattr(route, "path", None) or "unmatched"
                self.metrics.requests.labels(path, str(status)).inc()
                self.metrics.latency.labels(path).observe(time.perf_counter() - start)

    async def _handle(self, scope: Scope, receive: Receive, send: Send) -> None:
        self.arrivals += 1
        headers = dict(scope["headers"])
        path, limit = scope["path"], self.settings.max_body_bytes
        guarded = path.startswith("/v1/") or (path == "/metrics" and self.settings.metrics_require_key)
        if guarded and not key_matches(self.settings, headers.get(b"x-api-key")):
            await _reply(send, 401, "missing or wrong X-API-Key header")
            return
        length = headers.get(b"content-length", b"")
        if length.isdigit() and int(length) > limit:
            await _reply(send, 413, f"body of {int(length)} bytes exceeds the limit of {limit} bytes")
            return
        if scope["method"] not in ("POST", "PUT", "PATCH"):
            await self.app(scope, receive, send)
            return
        if not self._admit(scope, headers, int(length) if length.isdigit() else 0):
            self.metrics.shed.inc()
            wait_s = max(self.state.batcher.estimated_wait_s(), self.completions.wait_s())
            await _shed(send, wait_s, self.settings.request_deadline_s)
            return
        if scope["state"].get("small", False):
            self.completions.started()
            scope["state"]["counted_since"] = time.perf_counter()
        try:
            await self._after_arrivals()
            body = await _read_body(receive, limit)
            if body is None:  # the client left while sending
                return
            scope["state"]["body_read"] = time.perf_counter()
            if isinstance(body, int):
                detail = f"body exceeds the limit of {limit} bytes (stopped reading after {body} bytes)"
                await _reply(send, 413, detail, drain=receive)
                return
            await self.app(scope, _replay(body, receive), send)
        finally:
            batcher = getattr(self.state, "batcher", None)
            if batcher is not None and scope["state"].get("reserved"):
                batcher.release(scope["state"])

    async def _after_arrivals(self) -> None:
        """Wait for this request's turn to be parsed, which takes a few milliseconds on the event loop: one request
        per turn of the loop, and only once a turn has passed with no new request (or ``MAX_PARSE_WAIT_S`` has).
        In a burst, every request passes its admission, and the refused ones are answered, before the admitted ones
        hold the loop; without a burst this costs two turns of the loop."""
        loop = asyncio.get_running_loop()
        since = time.monotonic()
        while True:
            seen = self.arrivals
            # Two turns: in the first, this task runs before the requests whose bytes arrived in that turn
            # have started; in the second, after they have passed their admission.
            await asyncio.sleep(0)
            await asyncio.sleep(0)
            quiet = self.arrivals == seen or time.monotonic() - since > MAX_PARSE_WAIT_S
            if quiet and not self.parse_turn_taken:
                self.parse_turn_taken = True
                loop.call_soon(self._free_parse_turn)
                return

    def _free_parse_turn(self) -> None:
        self.parse_turn_taken = False

    def _admit(self, scope: Scope, headers: dict[bytes, bytes], length: int) -> bool:
        """Reserve the request's estimated first turn in the queue (False: shed it). Only POSTs to ``/v1/*``."""
        scope.setdefault("state", {})
        batcher = getattr(self.state, "batcher", None)
        if batcher is None or not scope["path"].startswith("/v1/"):
            return True
        if scope["state"].get(PROBE):
            scope["state"]["small"] = True
            return True
        deadline_s = self.settings.request_deadline_s
        binary = headers.get(b"content-type", b"").startswith(b"application/octet-stream")
        windows = max(1, length // (BINARY_BYTES_PER_WINDOW if binary else JSON_BYTES_PER_WINDOW))
        first_turn = min(windows, batcher.chunk)
        small = windows <= SMALL_REQUEST_WINDOWS
        wait_s = batcher.estimated_wait_s(first_turn, requests=1)
        if wait_s > deadline_s or (small and self.completions.wait_s() > COMPLETION_DEADLINE_SHARE * deadline_s):
            return False
        scope["state"]["small"] = small
        batcher.reserved += first_turn
        batcher.reserved_requests += 1
        scope["state"]["reserved"] = first_turn
        scope["state"]["start_by"] = time.monotonic() + deadline_s
        return True


async def _read_body(receive: Receive, limit: int) -> bytes | int | None:
    """The whole body; or, past ``limit``, the number of bytes read when reading stopped (the rest is never read and
    what was read is let go at once); None if the client left."""
    chunks: list[bytes] = []
    size = 0
    while True:
        message = await receive()
        if message["type"] == "http.disconnect":
            return None
        chunk = message.get("body", b"")
        size += len(chunk)
        if size > limit:
            return size
        if not message.get("more_body", False):
            return chunk if not chunks else b"".join([*chunks, chunk])  # one message (the usual case): no copy
        chunks.append(chunk)


def _replay(body: bytes, receive: Receive) -> Receive:
    """A ``receive`` that hands the route the body read already, then the client's later messages (disconnect)."""
    sent = False

    async def replay() -> Message:
        nonlocal sent
        if not sent:
            sent = True
            return {"type": "http.request", "body": body, "more_body": False}
        return await receive()

    return replay


async def _shed(send: Send, wait_s: float, deadline_s: float) -> None:
    exc = Overloaded(wait_s, deadline_s)
    await _send(send, error_response(503, str(exc), {"Retry-After": str(exc.retry_after_s)}))


async def _reply(send: Send, status: int, detail: str, drain: Receive | None = None) -> None:
    await _send(send, error_response(status, detail), drain)


async def _send(send: Send, response: Any, drain: Receive | None = None) -> None:
    """Send ``response``; with ``drain``, read and discard what the client still sends (bounded) before ending it.

    A server that closes a connection with unread request bytes makes the kernel answer with a reset, which can
    destroy the error answer before the client reads it; reading the rest first (and throwing it away: memory
    stays flat) lets a client that writes its whole body before reading see the 413.
    """
    await send({"type": "http.response.start", "status": response.status_code, "headers": response.raw_headers})
    await send({"type": "http.response.body", "body": response.body, "more_body": drain is not None})
    if drain is None:
        return
    deadline, discarded = time.monotonic() + DRAIN_SECONDS, 0
    while time.monotonic() < deadline and discarded < DRAIN_BYTES:
        message = await drain()
        discarded += len(message.get("body", b""))
        if message["type"] == "http.disconnect" or not message.get("more_body", False):
            break
    await send({"type": "http.response.body", "body": b""})
