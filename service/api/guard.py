"""Pure ASGI middleware in front of every HTTP request: body-size limit, optional API key, metrics.

Plain ASGI rather than ``@app.middleware("http")``: that wrapper costs about a millisecond per request
(measured with ``benchmarks.bench_service``), a fifth of the single-window latency budget.
"""

from __future__ import annotations

import json
import time
from collections.abc import Awaitable, Callable, MutableMapping
from typing import Any

from service.api.metrics import ServiceMetrics
from service.settings import Settings

Scope = MutableMapping[str, Any]
Message = MutableMapping[str, Any]
Receive = Callable[[], Awaitable[Message]]
Send = Callable[[Message], Awaitable[None]]
ASGIApp = Callable[[Scope, Receive, Send], Awaitable[None]]


class Guard:
    def __init__(self, app: ASGIApp, settings: Settings, metrics: ServiceMetrics) -> None:
        self.app, self.settings, self.metrics = app, settings, metrics

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        start = time.perf_counter()
        status = 500
        headers = dict(scope["headers"])
        length = headers.get(b"content-length", b"")
        key = self.settings.api_key

        async def tracked(message: Message) -> None:
            nonlocal status
            if message["type"] == "http.response.start":
                status = message["status"]
            await send(message)

        if length.isdigit() and int(length) > self.settings.max_body_bytes:
            detail = f"body of {int(length)} bytes exceeds the limit of {self.settings.max_body_bytes} bytes"
            await _reply(tracked, 413, detail)
        elif key and scope["path"].startswith("/v1/") and headers.get(b"x-api-key") != key.encode():
            await _reply(tracked, 401, "missing or wrong X-API-Key header")
        else:
            await self.app(scope, receive, tracked)
        # The route template, not the raw path: label values stay bounded whatever clients send.
        route = scope.get("route")
        path = getattr(route, "path", None) or "unmatched"
        self.metrics.requests.labels(path, str(status)).inc()
        self.metrics.latency.labels(path).observe(time.perf_counter() - start)


async def _reply(send: Send, status: int, detail: str) -> None:
    body = json.dumps({"detail": detail}).encode()
    headers = [(b"content-type", b"application/json"), (b"content-length", str(len(body)).encode())]
    await send({"type": "http.response.start", "status": status, "headers": headers})
    await send({"type": "http.response.body", "body": body})
