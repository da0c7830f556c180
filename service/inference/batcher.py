"""Micro-batching: concurrent requests and streams share onnxruntime calls.

Callers ``await batcher.infer(windows)``; a single worker task takes every window already queued (up
to ``max_batch``), runs the models in a worker thread (never on the event loop) and hands each caller
its rows. It does not wait for company by default (``max_wait_ms`` = 0): a lone request runs at once,
and whatever arrives while a batch runs forms the next batch, so batches grow with load by themselves.
A positive ``max_wait_ms`` additionally waits that long after the first window for more.
"""

from __future__ import annotations

import asyncio
import time
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

RunModels = Callable[[np.ndarray], tuple[np.ndarray, np.ndarray | None]]


@dataclass
class _Pending:
    imu: np.ndarray
    future: asyncio.Future


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

    async def infer(self, imu: np.ndarray) -> tuple[np.ndarray, np.ndarray | None]:
        future: asyncio.Future = asyncio.get_running_loop().create_future()
        await self.queue.put(_Pending(imu, future))
        return await future

    async def _worker(self) -> None:
        while True:
            batch = [await self.queue.get()]
            size = len(batch[0].imu)
            while size < self.max_batch and not self.queue.empty():
                batch.append(self.queue.get_nowait())
                size += len(batch[-1].imu)
            deadline = time.monotonic() + self.max_wait_s
            while size < self.max_batch and self.max_wait_s > 0:
                timeout = deadline - time.monotonic()
                if timeout <= 0:
                    break
                try:
                    item = await asyncio.wait_for(self.queue.get(), timeout)
                except TimeoutError:
                    break
                batch.append(item)
                size += len(item.imu)
            await self._run(batch)

    async def _run(self, batch: list[_Pending]) -> None:
        imu = np.concatenate([p.imu for p in batch])
        start = time.perf_counter()
        try:
            probs, quats = await asyncio.to_thread(self.run, imu)
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
