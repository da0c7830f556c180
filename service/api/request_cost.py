"""What a small request costs the service, as the busy service's seconds between answers (``Completions``), and the
start-up probe that measures it before the first client's answer (``seed_request_cost``). The guard sheds a burst
by it (``service.api.guard``)."""

from __future__ import annotations

import asyncio
import time
from collections import deque
from collections.abc import Awaitable, Callable, MutableMapping
from typing import Any

import orjson

Message = MutableMapping[str, Any]
ASGIApp = Callable[
    [MutableMapping[str, Any], Callable[[], Awaitable[Message]], Callable[[Message], Awaitable[None]]], Awaitable[None]
]
PROBE = "wearmocap_probe"  # scope state of the start-up probe's requests: always admitted, never in /metrics
COMPLETION_WINDOW = 256  # answers the seconds between answers are averaged over
# the share of the deadline the small requests admitted may fill by ``Completions``' estimate: the seconds between
# answers of a busy service vary from one burst to the next (the same 1,000-request burst took 1.0-1.9 s), and a
# request admitted on an estimate that was too low is refused late, after its body was parsed
COMPLETION_DEADLINE_SHARE = 0.75


class Completions:
    """How long the small requests admitted now will take to be answered: the number not yet answered times the
    seconds between answers while the service is busy, averaged over the last ``COMPLETION_WINDOW`` answers (when
    idle, a request's own time). A mean over many answers, not a moving average of the last few: answers come in
    clumps (one inference batch answers many requests within microseconds), and the last few gaps say nothing of
    the rate."""

    def __init__(self) -> None:
        self.pending = 0
        self.gaps_s: deque[float] = deque(maxlen=COMPLETION_WINDOW)
        self.last_end = 0.0

    @property
    def seconds_per_request(self) -> float:
        return sum(self.gaps_s) / len(self.gaps_s) if self.gaps_s else 0.0

    def wait_s(self) -> float:
        return (self.pending + 1) * self.seconds_per_request

    def started(self) -> None:
        self.pending += 1

    def ended(self, started_at: float, answered: bool) -> None:
        """A request ended; ``answered``: with a 2xx (a refusal or an error says nothing of the cost of work)."""
        now = time.perf_counter()
        self.pending -= 1
        if answered:
            self.gaps_s.append(now - max(started_at, self.last_end))  # busy: the time since the previous answer
            self.last_end = now


async def seed_request_cost(app: ASGIApp, api_key: str | None, rounds: int = 6, at_once: int = 8) -> None:
    """Send a few rounds of single-window requests, several at once, through the whole application (this guard,
    parsing, inference, the answer), in process, so that ``Completions`` knows the seconds between answers of a
    busy service before the first client's answer: a burst on a service just started is then shed at arrival
    instead of admitted whole. They are always admitted and not counted in /metrics."""
    body = orjson.dumps({"windows": [{"samples": [[0.0, 0.0, 9.81, 0.0, 0.0, 0.0]] * 128}]})
    headers = [(b"content-type", b"application/json"), (b"content-length", str(len(body)).encode())]
    if api_key:
        headers.append((b"x-api-key", api_key.encode()))
    for _ in range(rounds):
        await asyncio.gather(*(_one_request(app, body, headers) for _ in range(at_once)))


async def _one_request(app: ASGIApp, body: bytes, headers: list[tuple[bytes, bytes]]) -> None:
    """One POST /v1/imu/windows through ``app``, its answer thrown away."""
    sent = False

    async def receive() -> Message:
        nonlocal sent
        if sent:
            await asyncio.sleep(3600)  # no disconnect while the answer is made
        sent = True
        return {"type": "http.request", "body": body, "more_body": False}

    async def send(message: Message) -> None:
        return None

    scope = {
        "type": "http",
        "asgi": {"version": "3.0"},
        "http_version": "1.1",
        "method": "POST",
        "scheme": "http",
        "path": "/v1/imu/windows",
        "raw_path": b"/v1/imu/windows",
        "query_string": b"",
        "root_path": "",
        "headers": headers,
        "client": ("127.0.0.1", 0),
        "server": ("127.0.0.1", 0),
        "state": {PROBE: True},
    }
    await app(scope, receive, send)
