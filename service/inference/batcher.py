"""Micro-batching: concurrent requests and streams share onnxruntime calls.

Callers ``await batcher.infer(windows)``; a single worker task takes every window already queued (up
to ``max_batch``), runs the models in ``run``'s worker threads (never on the event loop) and hands each caller
its rows. It does not wait for company by default (``max_wait_ms`` = 0): a lone request runs at once,
and whatever arrives while a batch runs forms the next batch, so batches grow with load by themselves.
A positive wait (the batcher's default, or per call: streams pass a longer one) keeps a batch open for
more windows until the deadline of its most impatient caller: larger batches cost less CPU per window.
"""

from __future__ import annotations

import asyncio
import time
from collections.abc import Awaitable, Callable
from dataclasses import dataclass

import numpy as np

RunModels = Callable[[np.ndarray], Awaitable[tuple[np.ndarray, np.ndarray | None]]]


@dataclass
class _Pending:
    imu: np.ndarray
    future: asyncio.Future
    deadline: float  # monotonic time by which this caller's windows must be running


class MicroBatcher:
    def __init__(
        self, run: RunModels, max_batch: int, max_wait_ms: float, on_batch: Callable[[int, float], None] | None = None
    ) -> None:
        self.run, self.max_batch, self.max_wait_s = run, max_batch, max_wait_ms / 1000.0
        self.on_batch = on_batch
        self.queue: asyncio.Queue[_Pending] = asyncio.Queue()
        self.task: asyncio.Task | None = None

    def start(self) -> None:
        self.task = asyncio.create_task(self._worker())

    async def stop(self) -> None:
        if self.task:
            self.task.cancel()
            try:
                await self.task
            except asyncio.CancelledError:
                pass

    async def infer(self, imu: np.ndarray, max_wait_ms: float | None = None) -> tuple[np.ndarray, np.ndarray | None]:
        """Rows of the models' outputs for ``imu``; ``max_wait_ms`` overrides the batcher's wait for company
        (streams, whose next window is 16 samples away, can wait longer than a request that someone awaits)."""
        wait_s = self.max_wait_s if max_wait_ms is None else max_wait_ms / 1000.0
        future: asyncio.Future = asyncio.get_running_loop().create_future()
        await self.queue.put(_Pending(imu, future, time.monotonic() + wait_s))
        return await future

    async def _worker(self) -> None:
        while True:
            batch = [await self.queue.get()]
            size, deadline = len(batch[0].imu), batch[0].deadline
            while size < self.max_batch:
                # Take what is queued at once; then wait only until the most impatient caller's deadline.
                if self.queue.empty():
                    timeout = deadline - time.monotonic()
                    if timeout <= 0:
                        break
                    try:
                        item = await asyncio.wait_for(self.queue.get(), timeout)
                    except TimeoutError:
                        break
                else:
                    item = self.queue.get_nowait()
                batch.append(item)
                size, deadline = size + len(item.imu), min(deadline, item.deadline)
            await self._run(batch)

    async def _run(self, batch: list[_Pending]) -> None:
        imu = np.concatenate([p.imu for p in batch])
        start = time.perf_counter()
        try:
            probs, quats = await self.run(imu)
        except Exception as exc:  # a model failure reaches every waiting caller
            for p in batch:
                if not p.future.done():
                    p.future.set_exception(exc)
            return
        if self.on_batch:
            self.on_batch(len(imu), time.perf_counter() - start)
        lo = 0
        for p in batch:
            hi = lo + len(p.imu)
            if not p.future.done():
                p.future.set_result((probs[lo:hi], None if quats is None else quats[lo:hi]))
            lo = hi
