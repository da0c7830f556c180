"""Runs the I2S models on a batch: small chunks × models spread over a pool of single-threaded runs.

Measured on the 2-core CI machine (``python -m benchmarks.bench_ort_vs_torch`` has the numbers): one
onnxruntime session per model with one intra-op thread, called concurrently from ``threads`` workers on
chunks of ``chunk`` windows, beats one call with two intra-op threads — the recurrent layers parallelise
poorly inside a call, small chunks stay in cache, and a single window runs its two models side by side.
onnxruntime sessions are safe to call from several threads at once.

The service's scheduler (``service.inference.batcher``) hands the pool one chunk at a time per worker
(``run_chunk_async``: both models in one thread), so that it can interleave callers fairly; ``__call__`` runs a
whole batch at once (chunks × models over the pool), for offline use.
"""

from __future__ import annotations

import asyncio
import time
from concurrent.futures import Future, ThreadPoolExecutor

import numpy as np

from service.inference.registry import LoadedModel

ASSIGNMENT, ALIGNMENT = "i2s_assignment", "i2s_alignment"


class ModelRunner:
    def __init__(self, models: dict[str, LoadedModel], threads: int, chunk: int) -> None:
        self.models, self.chunk = models, chunk
        self.pool = ThreadPoolExecutor(max_workers=threads, thread_name_prefix="onnxruntime")

    def _submit(self, imu: np.ndarray) -> dict[str, list[Future]]:
        tasks = [ASSIGNMENT] + ([ALIGNMENT] if ALIGNMENT in self.models else [])
        chunks = [imu[i : i + self.chunk] for i in range(0, len(imu), self.chunk)]
        return {task: [self.pool.submit(self.models[task].run, c) for c in chunks] for task in tasks}

    def __call__(self, imu: np.ndarray) -> tuple[np.ndarray, np.ndarray | None]:
        """``(B, 128, 6)`` → probabilities ``(B, 7)`` and, if an alignment model is loaded, ``(B, 7, 4)``."""
        out = {task: np.concatenate([f.result() for f in fs]) for task, fs in self._submit(imu).items()}
        return out[ASSIGNMENT], out.get(ALIGNMENT)

    def run_chunk(self, imu: np.ndarray) -> tuple[np.ndarray, np.ndarray | None]:
        """One chunk through every I2S model in the calling thread: probabilities and, if loaded, alignments."""
        probs = self.models[ASSIGNMENT].run(imu)
        return probs, self.models[ALIGNMENT].run(imu) if ALIGNMENT in self.models else None

    async def run_chunk_async(self, imu: np.ndarray) -> tuple[np.ndarray, np.ndarray | None]:
        """``run_chunk`` on one worker thread, off the event loop (the scheduler's unit of work)."""
        return await asyncio.wrap_future(self.pool.submit(self.run_chunk, imu))

    async def run_model(self, task: str, x: np.ndarray) -> np.ndarray:
        """One model (e.g. a pose model) on its input, in the same worker threads, without batching."""
        return await asyncio.wrap_future(self.pool.submit(self.models[task].run, x))

    async def run_call(self, fn, *args):
        """Any call (a pose request's whole computation) in the same worker threads, off the event loop."""
        return await asyncio.wrap_future(self.pool.submit(fn, *args))

    async def run_call_timed(self, fn, *args):
        """``run_call`` and the seconds the call itself took in its worker thread (not its wait for one)."""

        def timed():
            start = time.perf_counter()
            result = fn(*args)
            return result, time.perf_counter() - start

        return await asyncio.wrap_future(self.pool.submit(timed))

    def close(self) -> None:
        self.pool.shutdown(wait=False, cancel_futures=True)
