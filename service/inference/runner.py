"""Runs the I2S models on a batch: small chunks × models spread over a pool of single-threaded runs.

Measured on the 2-core CI machine (``python -m benchmarks.bench_ort_vs_torch`` has the numbers): one
onnxruntime session per model with one intra-op thread, called concurrently from ``threads`` workers on
chunks of ``chunk`` windows, beats one call with two intra-op threads — the recurrent layers parallelise
poorly inside a call, small chunks stay in cache, and a single window runs its two models side by side.
onnxruntime sessions are safe to call from several threads at once.

The service's scheduler (``service.inference.batcher``) hands the pool about one chunk per worker at a time
(``run_chunk_async``), so that it can interleave callers fairly; ``__call__`` runs a whole batch at once (chunks ×
models over the pool), for offline use.
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

    async def run_chunk_async(self, imu: np.ndarray) -> tuple[np.ndarray, np.ndarray | None, float]:
        """One chunk through every I2S model, each model a task of the pool (a lone window runs its two models side
        by side), off the event loop: the scheduler's unit of work. Also the worker-seconds the models took in
        their threads (not their wait for a thread) and those threads' CPU seconds (onnxruntime runs each model in
        the calling thread: one intra-op thread)."""
        futures = {
            task: self.pool.submit(_timed, self.models[task].run, imu)
            for task in (ASSIGNMENT, ALIGNMENT)
            if task in self.models
        }
        out = {task: await asyncio.wrap_future(f) for task, f in futures.items()}
        seconds = sum(t for _, t, _ in out.values())
        cpu_seconds = sum(c for _, _, c in out.values())
        return out[ASSIGNMENT][0], out[ALIGNMENT][0] if ALIGNMENT in out else None, seconds, cpu_seconds

    async def run_model(self, task: str, x: np.ndarray) -> np.ndarray:
        """One model (e.g. a pose model) on its input, in the same worker threads, without batching."""
        return await asyncio.wrap_future(self.pool.submit(self.models[task].run, x))

    async def run_call(self, fn, *args):
        """Any call (a pose request's whole computation) in the same worker threads, off the event loop."""
        return await asyncio.wrap_future(self.pool.submit(fn, *args))

    async def run_call_timed(self, fn, *args):
        """``run_call`` and the seconds the call itself took in its worker thread (not its wait for one)."""
        result, seconds, _ = await asyncio.wrap_future(self.pool.submit(_timed, fn, *args))
        return result, seconds

    def close(self) -> None:
        self.pool.shutdown(wait=False, cancel_futures=True)


def _timed(fn, *args):  # type: ignore[no-untyped-def]
    """``fn(*args)``, the seconds it took and the CPU seconds of the thread that runs it meanwhile."""
    start, cpu = time.perf_counter(), time.thread_time()
    result = fn(*args)
    return result, time.perf_counter() - start, time.thread_time() - cpu
