"""Batching live pose sessions onto the onnxruntime workers.

Each live pose session hands its new body frames to ``LivePoseBatcher.process`` and awaits its messages. A lone
session's frames run at once; whatever other sessions hand over while the workers are busy waits for the next free
worker and then runs as one batch (``service.inference.pose.process_live``: one network call per model and frame
count, the per-frame geometry as one array). So a busy service pays the per-call costs of numpy and onnxruntime
once per batch instead of once per session and packet, and nothing ever waits for company. A session has at most
one call in flight (its stream awaits each answer before it reads on), so its frames stay in order.

The service runs one batch at a time (``workers`` 1): a batch's network call and numpy work run while the event
loop reads the next packets, and the sessions that arrive meanwhile make the next batch larger rather than
competing with it for the cores. ``busy_share`` says how much of that one worker the live sessions take, and
``projected_busy_share`` how much with one more; stream admission refuses new pose sessions when that passes its
fraction.
"""

from __future__ import annotations

import asyncio
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from service.inference.pose import LivePose, PoseModel, process_live
from service.inference.runner import ModelRunner

BUSY_WINDOW_S = 2.0  # of recent batches, for ``busy_share``


@dataclass(eq=False)
class _Job:
    live: LivePose
    frames: np.ndarray
    first_frame: int
    future: asyncio.Future


class LivePoseBatcher:
    def __init__(
        self, runner: ModelRunner, workers: int, on_batch: Callable[[str, int, float], None] | None = None
    ) -> None:
        """``on_batch(model name, sessions, seconds)`` after every batch."""
        self.runner, self.workers, self.on_batch = runner, workers, on_batch
        self.pending: list[_Job] = []
        self.in_flight = 0
        self.batches: deque[tuple[float, float, float]] = deque(maxlen=4096)  # (end, worker-seconds, fixed part)
        self.per_batch_s: dict[str, float] = {}  # a model's fixed seconds per batch (``probe``)
        self.sessions = 0  # live pose sessions open now
        self.session_changes: deque[tuple[float, int]] = deque(maxlen=4096)  # (monotonic time, sessions from then)

    def busy_share(self, window_s: float = BUSY_WINDOW_S) -> float:
        """The share of the last ``window_s`` seconds the live pose batches kept their worker busy (measured in
        the worker's thread: it includes what the machine's other work costs them)."""
        since = time.monotonic() - window_s
        return sum(seconds for end, seconds, _ in self.batches if end >= since) / window_s

    def session_opened(self) -> None:
        self.sessions += 1
        self.session_changes.append((time.monotonic(), self.sessions))

    def session_closed(self) -> None:
        self.sessions -= 1
        self.session_changes.append((time.monotonic(), self.sessions))

    def projected_busy_share(self, window_s: float = BUSY_WINDOW_S) -> float:
        """``busy_share`` with the sessions open now and one more. Each session's share is what the window measured
        beyond the batches' fixed parts (``probe``), over the sessions open on average in it; the sessions opened
        since, and the new one, add that share each before their load shows in the measurement, so clients that
        arrive in a burst do not all get in."""
        now = time.monotonic()
        since, count, area = now - window_s, 0, 0.0
        for t, n in self.session_changes:
            if t > since:
                area += count * (t - since)
                since = t
            count = n
        area += count * (now - since)
        mean = area / window_s
        busy = self.busy_share(window_s)
        if mean < 1.0:
            return busy
        fixed = sum(part for end, _, part in self.batches if end >= now - window_s) / window_s
        per_session = max(busy - fixed, 0.0) / mean
        return busy + max(self.sessions + 1 - mean, 0.0) * per_session

    async def process(self, live: LivePose, frames: np.ndarray, first_frame: int) -> list[dict]:
        """The session's messages for its frames ``(m, N, 10)``."""
        job = _Job(live, frames, first_frame, asyncio.get_running_loop().create_future())
        self.pending.append(job)
        self._dispatch()
        return await job.future

    async def probe(self, model: PoseModel, sessions: int = 32, packet: int = 4) -> tuple[float, float]:
        """A streaming model's cost per batch (seconds, fixed) and per frame, measured on the workers: rounds of one
        session and of ``sessions`` sessions, ``packet`` frames each, after a warm-up."""
        frames = np.zeros((packet, len(model.spec.sensors), 10))
        frames[:, :, 2], frames[:, :, 6] = 9.81, 1.0  # at rest, upright
        identity = np.tile([1.0, 0.0, 0.0, 0.0], (len(model.spec.sensors), 1))
        lives = [LivePose(model, "declared", identity) for _ in range(sessions)]
        timings = {}
        for n in (1, sessions):
            jobs = [(live, frames, 0) for live in lives[:n]]
            await self.runner.run_call_timed(process_live, jobs)
            runs = [await self.runner.run_call_timed(process_live, jobs) for _ in range(4)]
            timings[n] = float(np.median([seconds for _, seconds in runs]))
        per_frame = max((timings[sessions] - timings[1]) / ((sessions - 1) * packet), 1e-7)
        self.per_batch_s[model.name] = max(timings[1] - packet * per_frame, 0.0)
        return self.per_batch_s[model.name], per_frame

    def _dispatch(self) -> None:
        while self.pending and self.in_flight < self.workers:
            jobs = [job for job in self.pending if not job.future.done()]  # a cancelled caller's frames are dropped
            self.pending = []
            by_model: dict[str, list[_Job]] = {}
            for job in jobs:
                by_model.setdefault(job.live.model.name, []).append(job)
            for model_jobs in by_model.values():
                self.in_flight += 1
                asyncio.ensure_future(self._run(model_jobs))

    async def _run(self, jobs: list[_Job]) -> None:
        try:
            messages, seconds = await self.runner.run_call_timed(
                process_live, [(job.live, job.frames, job.first_frame) for job in jobs]
            )
        except Exception as exc:  # a model failure reaches every session in the batch
            for job in jobs:
                if not job.future.done():
                    job.future.set_exception(exc)
            return
        finally:
            self.in_flight -= 1
            self._dispatch()
        self.batches.append((time.monotonic(), seconds, self.per_batch_s.get(jobs[0].live.model.name, 0.0)))
        if self.on_batch:
            self.on_batch(jobs[0].live.model.name, len(jobs), seconds)
        for job, answer in zip(jobs, messages, strict=True):
            if not job.future.done():
                job.future.set_result(answer)
