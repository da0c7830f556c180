"""Batching live pose sessions onto the onnxruntime workers (``service.inference.session_batcher``).

The frames that sessions hand over while a batch runs make up the next batch (``service.inference.pose.
process_live``: one network call per model and frame count, the per-frame geometry as one array).

The service runs one batch at a time (``workers`` 1): a batch's network call and numpy work run while the event
loop reads the next packets, and the sessions that arrive meanwhile make the next batch larger rather than
competing with it for the cores. ``busy_share`` says how much of that one worker the live sessions take, and
``projected_busy_share`` how much with one more; stream admission refuses new pose sessions when that passes its
fraction.
"""

from __future__ import annotations

import time
from collections import deque
from collections.abc import Callable

import numpy as np

from service.inference.pose import LivePose, PoseModel, cost_key, process_live
from service.inference.runner import ModelRunner
from service.inference.session_batcher import BUSY_WINDOW_S, SessionBatcher
from service.inference.velocity import VelocityModel


class LivePoseBatcher(SessionBatcher):
    def __init__(
        self, runner: ModelRunner, workers: int, on_batch: Callable[[str, int, float], None] | None = None
    ) -> None:
        """``on_batch(model name, sessions, seconds)`` after every batch."""
        count = None if on_batch is None else lambda name, calls, seconds: on_batch(name, len(calls), seconds)
        super().__init__(runner, process_live, workers, count)
        self.sessions = 0  # live pose sessions open now
        self.session_changes: deque[tuple[float, int]] = deque(maxlen=4096)  # (monotonic time, sessions from then)

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
        return await self.submit(live, frames, first_frame)

    async def probe(
        self, model: PoseModel, sessions: int = 32, packet: int = 4, velocity: VelocityModel | None = None
    ) -> tuple[float, float]:
        """A streaming model's cost per batch (seconds, fixed) and per frame (``SessionBatcher.probe``), with the
        learned translation's ``velocity`` model beside it where given: sessions at rest, upright, ``packet`` frames
        each."""
        frames = np.zeros((packet, len(model.spec.sensors), 10))
        frames[:, :, 2], frames[:, :, 6] = 9.81, 1.0  # at rest, upright
        identity = np.tile([1.0, 0.0, 0.0, 0.0], (len(model.spec.sensors), 1))
        translation = "none" if velocity is None else "learned"
        lives = [
            LivePose(model, "declared", identity, translation=translation, velocity=velocity) for _ in range(sessions)
        ]
        calls = lambda n: [(live, frames, 0) for live in lives[:n]]  # noqa: E731
        return await super().probe(cost_key(model, velocity), calls, sessions, packet)
