"""Batching live sessions onto the onnxruntime workers (live pose, live flex).

Each session hands its new readings to ``SessionBatcher.submit`` and awaits its answer. A lone session's readings
run at once; whatever other sessions hand over while the workers are busy waits for the next free worker and then
runs as one batch: one call of the batch function per model (``service.inference.pose.process_live``,
``service.inference.flex.process_live_flex``), one network call for all of them. So a busy service pays the
per-call costs of numpy and onnxruntime once per batch instead of once per session and packet, and nothing ever
waits for company. A session has at most one call in flight (its stream awaits each answer before it reads on),
so its readings stay in order and its state is touched by one thread at a time.
"""

from __future__ import annotations

import asyncio
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from service.inference.runner import ModelRunner

BUSY_WINDOW_S = 2.0  # of recent batches, for ``busy_share``


@dataclass(eq=False)
class _Job:
    live: Any  # a session's state, with ``.model.name``
    args: tuple
    future: asyncio.Future


class SessionBatcher:
    def __init__(
        self,
        runner: ModelRunner,
        batch: Callable[[list[tuple]], list],
        workers: int,
        on_batch: Callable[[str, list[tuple], float], None] | None = None,
    ) -> None:
        """``batch([(live, *args), ...])`` → one answer per job, run on the workers; ``on_batch(model name, the
        batch's jobs, seconds)`` after every batch."""
        self.runner, self.batch, self.workers, self.on_batch = runner, batch, workers, on_batch
        self.pending: list[_Job] = []
        self.in_flight = 0
        self.batches: deque[tuple[float, float, float]] = deque(maxlen=4096)  # (end, worker-seconds, fixed part)
        self.per_batch_s: dict[str, float] = {}  # a model's fixed seconds per batch, where measured

    def busy_share(self, window_s: float = BUSY_WINDOW_S) -> float:
        """The share of the last ``window_s`` seconds the batches kept their worker busy (measured in the worker's
        thread: it includes what the machine's other work costs them)."""
        since = time.monotonic() - window_s
        return sum(seconds for end, seconds, _ in self.batches if end >= since) / window_s

    async def probe(
        self, name: str, calls_for: Callable[[int], list[tuple]], sessions: int, frames_per_call: int
    ) -> tuple[float, float]:
        """A model's cost per batch (seconds, fixed) and per frame, measured on the workers: rounds of one session and
        of ``sessions`` sessions (``calls_for(n)``: a batch of n sessions' calls of ``frames_per_call`` frames each),
        after a warm-up. What one more session adds is the cost per frame; on an idle machine, as the I2S capacity
        is measured, since batches timed under load also time the event loop's share of the interpreter."""
        timings = {}
        for n in (1, sessions):
            await self.runner.run_call_timed(self.batch, calls_for(n))
            runs = [await self.runner.run_call_timed(self.batch, calls_for(n)) for _ in range(4)]
            timings[n] = float(np.median([seconds for _, seconds in runs]))
        per_frame = max((timings[sessions] - timings[1]) / ((sessions - 1) * frames_per_call), 1e-7)
        self.per_batch_s[name] = max(timings[1] - frames_per_call * per_frame, 0.0)
        return self.per_batch_s[name], per_frame

    async def submit(self, live: Any, *args: Any) -> Any:
        """The session's answer for its new readings (``args``)."""
        job = _Job(live, args, asyncio.get_running_loop().create_future())
        self.pending.append(job)
        self._dispatch()
        return await job.future

    def _dispatch(self) -> None:
        while self.pending and self.in_flight < self.workers:
            jobs = [job for job in self.pending if not job.future.done()]  # a cancelled caller's readings are dropped
            self.pending = []
            by_model: dict[str, list[_Job]] = {}
            for job in jobs:
                by_model.setdefault(job.live.model.name, []).append(job)
            for model_jobs in by_model.values():
                self.in_flight += 1
                asyncio.ensure_future(self._run(model_jobs))

    async def _run(self, jobs: list[_Job]) -> None:
        calls = [(job.live, *job.args) for job in jobs]
        try:
            answers, seconds = await self.runner.run_call_timed(self.batch, calls)
        except Exception as exc:  # a model failure reaches every session in the batch
            for job in jobs:
                if not job.future.done():
                    job.future.set_exception(exc)
            return
        finally:
            self.in_flight -= 1
            self._dispatch()
        name = jobs[0].live.model.name
        # the batch's fixed part: the dearest of what its sessions run (a live pose session's pose model, and its
        # velocity model beside it: ``LivePose.cost_key``), as probed
        fixed = max(self.per_batch_s.get(getattr(job.live, "cost_key", name), 0.0) for job in jobs)
        self.batches.append((time.monotonic(), seconds, fixed))
        if self.on_batch:
            self.on_batch(name, calls, seconds)
        for job, answer in zip(jobs, answers, strict=True):
            if not job.future.done():
                job.future.set_result(answer)
