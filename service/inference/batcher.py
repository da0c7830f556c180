"""Fair, deadline-aware scheduling of IMU windows onto the onnxruntime workers.

Callers ``await batcher.infer(windows)``. Windows run in chunks of at most ``chunk`` windows, one chunk per
worker thread at a time plus ``spare`` (1) waiting in the pool, so that no worker idles while the event loop is
busy parsing a request, and each caller gets its rows as soon as its own chunks are done.

Fairness rule: the queued callers (REST requests and stream sessions alike) take turns. A turn takes at most one
chunk of a caller's windows; callers with fewer windows share a chunk. A caller with windows left goes to the back
of the line after its turn, and a new caller goes ahead of every caller that has had a turn already, in a chunk of
new callers only. So a single window waits for the chunks already running and for the new callers ahead of it,
never for the rest of a 4,096-window batch.

Batching for company: by default a lone window runs at once, and whatever arrives while chunks run fills the
next ones (``max_wait_ms`` = 0). A positive wait (the batcher's default, or per call: streams pass a longer one)
lets a part-filled chunk wait for more windows until its most impatient caller's deadline.

Deadlines and load shedding: a REST caller passes the monotonic time by which its work must start. If the
estimated wait (the windows ahead of it, one turn each, at the measured seconds per window) passes it, ``infer``
raises ``Overloaded`` at once instead of queueing; a caller whose deadline passes while queued anyway (the
estimate was wrong) gets ``Overloaded`` when its turn comes. A caller that is cancelled (its client went away)
leaves the line: none of its remaining windows are computed.
"""

from __future__ import annotations

import asyncio
import math
import time
from collections import deque
from collections.abc import Awaitable, Callable
from dataclasses import dataclass

import numpy as np

# One chunk → (probabilities, alignments or None, worker-seconds it took in the workers' threads (wall), the CPU
# seconds of those threads).
RunChunk = Callable[[np.ndarray], Awaitable[tuple[np.ndarray, np.ndarray | None, float, float]]]
EWMA_WEIGHT = 0.2  # of the newest chunk in the seconds-per-window estimates
SMALL_CHUNK = 2  # windows: the chunk size that stands for live streams' (a few windows at a time)


def _ewma(old: float | None, new: float) -> float:
    return new if old is None else (1 - EWMA_WEIGHT) * old + EWMA_WEIGHT * new


class Overloaded(Exception):
    """The estimated wait passes the caller's deadline: answer 503 with ``Retry-After``."""

    def __init__(self, wait_s: float, budget_s: float) -> None:
        self.wait_s, self.budget_s = wait_s, budget_s
        self.retry_after_s = max(1, math.ceil(wait_s - max(budget_s, 0.0)))
        super().__init__(
            f"overloaded: the estimated wait of {wait_s:.2f} s passes this request's deadline "
            f"(time left {max(budget_s, 0.0):.2f} s); retry in {self.retry_after_s} s"
        )


@dataclass(eq=False)
class _Job:
    imu: np.ndarray  # (n, 128, 6)
    future: asyncio.Future
    company_until: float  # monotonic time until which its windows may wait for company
    start_by: float | None  # monotonic time by which its first chunk must start (REST); None: no deadline
    next: int = 0  # first window not yet dispatched
    done: int = 0
    probs: np.ndarray | None = None
    quats: np.ndarray | None = None

    @property
    def remaining(self) -> int:
        return len(self.imu) - self.next

    def store(self, lo: int, hi: int, probs: np.ndarray, quats: np.ndarray | None) -> None:
        if self.probs is None:
            self.probs = np.empty((len(self.imu), *probs.shape[1:]), probs.dtype)
            if quats is not None:
                self.quats = np.empty((len(self.imu), *quats.shape[1:]), quats.dtype)
        self.probs[lo:hi] = probs
        if quats is not None and self.quats is not None:
            self.quats[lo:hi] = quats
        self.done += hi - lo
        if self.done == len(self.imu) and not self.future.done():
            self.future.set_result((self.probs, self.quats))


class MicroBatcher:
    def __init__(
        self,
        run_chunk: RunChunk,
        workers: int,
        chunk: int,
        max_wait_ms: float,
        on_batch: Callable[[int, float], None] | None = None,
        spare: int = 2,
    ) -> None:
        self.run_chunk, self.workers, self.chunk, self.spare = run_chunk, workers, chunk, spare
        self.max_wait_s = max_wait_ms / 1000.0
        self.on_batch = on_batch
        self.jobs: deque[_Job] = deque()
        self.in_flight_windows: list[int] = []
        self.wake = asyncio.Event()
        self.task: asyncio.Task | None = None
        self.seconds_per_window: float | None = None  # worker-seconds per window in full chunks (in their threads)
        self.seconds_per_small_window: float | None = None  # the same in chunks of SMALL_CHUNK windows
        # CPU seconds per window in chunks of SMALL_CHUNK: what the stream admission reads. A burst of REST requests
        # (their parsing holds the interpreter; their clients share the cores) stretches the chunks' wall time, not
        # their CPU time; an estimate in wall time kept the streams that came after a burst at a fraction of what
        # the workers hold (119 of 200 sensors admitted with the workers 31 % busy).
        self.cpu_seconds_per_small_window: float | None = None
        self.capacity_fixed = False  # set by the operator (``set_capacity``): never refined by measurement
        self.reserved = 0  # windows of admitted requests whose bodies are still being read or parsed
        self.reserved_requests = 0
        self.request_overhead_s = 0.0  # event-loop time to parse one request (EWMA, measured by the routes)
        self.abandoned = 0  # windows not computed because their caller went away

    def start(self) -> None:
        self.task = asyncio.create_task(self._dispatch())

    async def stop(self) -> None:
        if self.task:
            self.task.cancel()
            try:
                await self.task
            except asyncio.CancelledError:
                pass

    @property
    def capacity_windows_per_s(self) -> float | None:
        return None if not self.seconds_per_window else self.workers / self.seconds_per_window

    def set_capacity(self, windows_per_s: float) -> None:
        """Fix the capacity: the chunks run from now on do not change it."""
        self.seconds_per_window = self.seconds_per_small_window = self.workers / windows_per_s
        self.cpu_seconds_per_small_window = self.seconds_per_small_window
        self.capacity_fixed = True

    async def probe(self, make_chunk: Callable[[int], np.ndarray]) -> float:
        """Measure full chunks, and chunks of ``SMALL_CHUNK`` windows, on every worker at once (after a warm-up
        round), as they run under load: the workers share the cores with each other and the event loop. Returns the
        capacity in windows/s."""
        for size in (self.chunk, min(SMALL_CHUNK, self.chunk)):
            x = make_chunk(size)
            await asyncio.gather(*(self.run_chunk(x) for _ in range(self.workers)))
            runs = await asyncio.gather(*(self.run_chunk(x) for _ in range(2 * self.workers)))
            wall, cpu = (max(sum(run[k] for run in runs) / (2 * self.workers * size), 1e-7) for k in (2, 3))
            if size == self.chunk:
                self.seconds_per_window = wall
            else:
                self.seconds_per_small_window, self.cpu_seconds_per_small_window = wall, cpu
        return self.workers / self.seconds_per_window

    @property
    def stream_capacity_windows_per_s(self) -> float | None:
        """Capacity for live streams: their windows come a few at a time, in small chunks, which cost more per
        window than full ones (on the 2-core machine 9.9 against 8.4 ms for the served assignment model); in CPU
        seconds, so that another load's contention does not count (the admission's ``fraction`` leaves room for it,
        and its latency checks refuse when the admitted streams' answers slow down)."""
        spw = self.stream_seconds_per_window
        return None if not spw else self.workers / spw

    @property
    def stream_seconds_per_window(self) -> float | None:
        """The cost of one stream window in the unit of ``stream_capacity_windows_per_s`` (CPU seconds): what a live
        pose or flex session's seconds per frame are converted to windows by."""
        return self.cpu_seconds_per_small_window

    def estimated_wait_s(self, extra_windows: int = 0, requests: int = 0, parsed: bool = False) -> float:
        """Seconds before a caller queued now (after ``extra_windows`` more) gets its first turn: the windows ahead of
        it at the measured seconds per window; for a request not parsed yet, also the admitted requests whose bodies
        are still being read or parsed (and ``requests`` more), with the event loop's time to parse them. A request
        ``parsed`` already is ahead of those, so they do not count for it."""
        if not self.seconds_per_window:
            return 0.0
        ahead = sum(min(job.remaining, self.chunk) for job in self.jobs) + sum(self.in_flight_windows)
        if parsed:
            return (ahead + extra_windows) * self.seconds_per_window / self.workers
        inference = (ahead + self.reserved + extra_windows) * self.seconds_per_window / self.workers
        return inference + (self.reserved_requests + requests) * self.request_overhead_s

    def release(self, state: dict) -> None:
        """An admitted request reached the queue or ended: its reservation (``state``: the Guard's) is returned."""
        if state.get("reserved"):
            self.reserved -= state["reserved"]
            self.reserved_requests -= 1
            state["reserved"] = 0

    def observe_request_overhead(self, seconds: float) -> None:
        """One request's parse and validation time on the event loop (EWMA)."""
        old = self.request_overhead_s
        self.request_overhead_s = seconds if not old else (1 - EWMA_WEIGHT) * old + EWMA_WEIGHT * seconds

    async def infer(
        self, imu: np.ndarray, max_wait_ms: float | None = None, start_by: float | None = None
    ) -> tuple[np.ndarray, np.ndarray | None]:
        """Rows of the models' outputs for ``imu`` ``(n, 128, 6)``. ``max_wait_ms`` overrides the batcher's wait for
        company; ``start_by`` (monotonic seconds) is the deadline by which the work must start, else
        ``Overloaded``."""
        now = time.monotonic()
        if start_by is not None:
            wait = self.estimated_wait_s(min(len(imu), self.chunk), parsed=True)
            if now + wait > start_by:
                raise Overloaded(wait, start_by - now)
        wait_s = self.max_wait_s if max_wait_ms is None else max_wait_ms / 1000.0
        job = _Job(imu, asyncio.get_running_loop().create_future(), now + wait_s, start_by)
        # New callers go ahead of those that have had a turn already (and behind earlier new callers).
        served = next((k for k, other in enumerate(self.jobs) if other.next > 0), len(self.jobs))
        self.jobs.insert(served, job)
        self.wake.set()
        try:
            return await job.future
        except asyncio.CancelledError:
            self.abandoned += job.remaining
            job.next = len(job.imu)  # nothing more of it is dispatched
            raise

    def _take_chunk(self, now: float) -> list[tuple[_Job, int, int]]:
        """One turn each, in line order, until a chunk is full; callers with windows left go to the back."""
        parts: list[tuple[_Job, int, int]] = []
        size, again = 0, []
        while self.jobs and size < self.chunk:
            job = self.jobs.popleft()
            if job.future.done() or not job.remaining:
                continue
            if parts and job.next > 0 and parts[0][1] == 0:
                self.jobs.appendleft(job)  # a chunk of new callers is not padded with a large caller's windows
                break
            if job.start_by is not None and job.next == 0 and now > job.start_by:
                job.future.set_exception(Overloaded(now - job.start_by, 0.0))
                continue
            n = min(job.remaining, self.chunk - size)
            parts.append((job, job.next, job.next + n))
            job.next += n
            size += n
            if job.remaining:
                again.append(job)
        self.jobs.extend(again)
        return parts

    def _company_wait_s(self, now: float) -> float:
        """How long a part-filled chunk may still wait for more windows (0: dispatch now)."""
        queued = sum(job.remaining for job in self.jobs if not job.future.done())
        if queued >= self.chunk or not self.jobs:
            return 0.0
        return max(0.0, min(job.company_until for job in self.jobs) - now)

    async def _dispatch(self) -> None:
        while True:
            if not self.jobs or len(self.in_flight_windows) >= self.workers + self.spare:
                self.wake.clear()
                await self.wake.wait()
                continue
            now = time.monotonic()
            wait = self._company_wait_s(now)
            if wait > 0:
                self.wake.clear()
                try:
                    await asyncio.wait_for(self.wake.wait(), wait)
                except TimeoutError:
                    pass
                if self._company_wait_s(time.monotonic()) > 0:
                    continue  # something arrived, but not enough: look again
            parts = self._take_chunk(time.monotonic())
            if parts:
                size = sum(hi - lo for _, lo, hi in parts)
                self.in_flight_windows.append(size)
                asyncio.ensure_future(self._run(parts, size))

    async def _run(self, parts: list[tuple[_Job, int, int]], size: int) -> None:
        imu = np.concatenate([job.imu[lo:hi] for job, lo, hi in parts])
        try:
            probs, quats, seconds, cpu_seconds = await self.run_chunk(imu)
        except Exception as exc:  # a model failure reaches every caller in the chunk
            for job, _, _ in parts:
                if not job.future.done():
                    job.future.set_exception(exc)
            return
        finally:
            self.in_flight_windows.remove(size)
            self.wake.set()
        if not self.capacity_fixed:
            self._refine(size, seconds, cpu_seconds)
        if self.on_batch:
            self.on_batch(size, seconds)
        row = 0
        for job, lo, hi in parts:
            if not job.future.done():
                job.store(lo, hi, probs[row : row + hi - lo], None if quats is None else quats[row : row + hi - lo])
            row += hi - lo

    def _refine(self, size: int, seconds: float, cpu_seconds: float) -> None:
        """Refine the measured cost per window from a chunk of ``size`` windows that took ``seconds`` (wall) and
        ``cpu_seconds`` in the workers' threads."""
        if size == self.chunk:
            self.seconds_per_window = _ewma(self.seconds_per_window, seconds / size)
        elif size == SMALL_CHUNK:
            self.seconds_per_small_window = _ewma(self.seconds_per_small_window, seconds / size)
            self.cpu_seconds_per_small_window = _ewma(self.cpu_seconds_per_small_window, cpu_seconds / size)
            # A full chunk costs no more per window than a small one. Full chunks run only under heavy load, whose
            # contention inflates their wall time in the threads, and after it none may come to correct that: a
            # small chunk that costs less per window than the full-chunk estimate proves it stale. Without this, a
            # burst of streams left the stream admission at a fraction of its capacity until the next burst.
            if self.seconds_per_window and self.seconds_per_small_window < self.seconds_per_window:
                self.seconds_per_window = self.seconds_per_small_window
