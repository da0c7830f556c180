"""The scheduler's policy: batching for company, one turn per caller, deadlines, dropped callers."""

from __future__ import annotations

import asyncio
import time

import numpy as np
import pytest

from service.inference.batcher import MicroBatcher, Overloaded


class _Recorder:
    """A stand-in for one worker's chunk run that records the chunks it gets (as the callers' ids)."""

    def __init__(self, seconds: float = 0.0, cpu_seconds: float | None = None) -> None:
        self.chunks: list[list[int]] = []
        self.seconds = seconds
        self.cpu_seconds = seconds if cpu_seconds is None else cpu_seconds

    async def __call__(self, imu: np.ndarray) -> tuple[np.ndarray, None, float, float]:
        self.chunks.append(imu[:, 0, 0].astype(int).tolist())
        await asyncio.sleep(self.seconds)
        return imu[:, 0, :1].copy(), None, self.seconds, self.cpu_seconds


def _windows(k: int, n: int = 1) -> np.ndarray:
    return np.full((n, 128, 6), float(k), dtype=np.float32)


def _run(calls: list[tuple[float, int, float | None]], seconds: float = 0.0, wait_ms: float = 0.0) -> list[list[int]]:
    """``calls``: (start delay s, windows, per-call wait ms); every caller must get its own rows back, in order."""

    async def main() -> list[list[int]]:
        rec = _Recorder(seconds)
        batcher = MicroBatcher(rec, workers=1, chunk=8, max_wait_ms=wait_ms, spare=0)
        batcher.start()

        async def one(k: int, delay: float, n: int, wait: float | None) -> None:
            await asyncio.sleep(delay)
            out, _ = await batcher.infer(_windows(k, n), wait)
            assert out.shape == (n, 1) and (out == k).all()

        await asyncio.gather(*(one(k, d, n, w) for k, (d, n, w) in enumerate(calls)))
        await batcher.stop()
        return rec.chunks

    return asyncio.run(main())


def test_a_lone_request_runs_at_once_and_load_fills_chunks() -> None:
    assert _run([(0.0, 1, None)]) == [[0]]
    # While the first chunk runs (50 ms), the next five callers queue and share one chunk.
    assert _run([(0.0, 1, None)] + [(0.01, 1, None)] * 5, seconds=0.05) == [[0], [1, 2, 3, 4, 5]]


def test_a_stream_window_waits_for_company_until_the_most_impatient_deadline() -> None:
    # Two stream windows (wait 100 ms) arriving 20 ms apart share one chunk ...
    assert _run([(0.0, 1, 100.0), (0.02, 1, 100.0)]) == [[0, 1]]
    # ... and a REST request (no wait) arriving meanwhile releases the chunk at once.
    start = time.monotonic()
    assert _run([(0.0, 1, 1000.0), (0.02, 1, 0.0)]) == [[0, 1]]
    assert time.monotonic() - start < 0.5


def test_a_single_window_takes_its_turn_between_the_chunks_of_a_large_batch() -> None:
    # A 64-window batch (8 chunks of 50 ms) starts first; a single window arriving 75 ms later, half-way through the
    # second chunk, runs on its own in the next chunk, not after the whole batch (nor padded with the batch's
    # windows). (Chunks of 10 ms and 15 ms left too little margin on a busy machine.)
    chunks = _run([(0.0, 64, None), (0.075, 1, None)], seconds=0.05)
    assert chunks[:2] == [[0] * 8, [0] * 8]
    assert chunks[2] == [1]
    assert sum(len(c) for c in chunks) == 65


def test_a_request_whose_wait_passes_its_deadline_is_refused_at_once_with_a_retry_time() -> None:
    async def main() -> None:
        rec = _Recorder(0.05)
        batcher = MicroBatcher(rec, workers=1, chunk=8, max_wait_ms=0.0, spare=0)
        batcher.set_capacity(80.0)  # 12.5 ms per window
        batcher.start()
        big = asyncio.ensure_future(batcher.infer(_windows(0, 400)))
        await asyncio.sleep(0.001)
        # Ahead of a new caller: the chunk running (8 windows) and the batch's next turn (8): 0.2 s.
        assert batcher.estimated_wait_s() == pytest.approx(16 * 0.0125)
        start = time.monotonic()
        with pytest.raises(Overloaded) as refused:
            await batcher.infer(_windows(1), start_by=time.monotonic() + 0.1)
        assert time.monotonic() - start < 0.05  # at once, not at the 0.1 s deadline (room for a busy machine)
        assert refused.value.retry_after_s == 1  # ceil(0.2125 - 0.1)
        # Requests admitted and still being read count for a request not parsed yet (the guard's estimate, 2.7 s
        # ahead), not for one parsed already: those reach the queue after it.
        batcher.reserved = 200
        assert batcher.estimated_wait_s(1) == pytest.approx(217 * 0.0125)
        out, _ = await batcher.infer(_windows(2), start_by=time.monotonic() + 1.0)  # 0.21 s: admitted
        assert out[0, 0] == 2
        big.cancel()
        await batcher.stop()

    asyncio.run(main())


def test_the_windows_of_a_caller_that_went_away_are_not_computed() -> None:
    async def main() -> None:
        rec = _Recorder(0.02)
        batcher = MicroBatcher(rec, workers=1, chunk=8, max_wait_ms=0.0, spare=0)
        batcher.start()
        first = asyncio.ensure_future(batcher.infer(_windows(0, 8)))
        gone = asyncio.ensure_future(batcher.infer(_windows(1, 80)))
        await asyncio.sleep(0.03)  # the first chunk of each has run or is running
        gone.cancel()
        await first
        await asyncio.sleep(0.1)
        computed = sum(c.count(1) for c in rec.chunks)
        assert computed <= 16 and batcher.abandoned >= 64
        assert batcher.estimated_wait_s() == 0.0 or not batcher.jobs
        await batcher.stop()

    asyncio.run(main())


def test_a_spare_chunk_waits_in_the_pool_so_no_worker_idles() -> None:
    async def main() -> list[int]:
        rec = _Recorder(0.02)
        batcher = MicroBatcher(rec, workers=1, chunk=8, max_wait_ms=0.0, spare=1)
        batcher.start()
        task = asyncio.ensure_future(batcher.infer(_windows(0, 64)))
        await asyncio.sleep(0.005)
        in_flight = list(batcher.in_flight_windows)
        await task
        await batcher.stop()
        return in_flight

    assert asyncio.run(main()) == [8, 8]  # one running, one waiting


def test_small_chunks_bring_down_a_full_chunk_cost_measured_under_contention() -> None:
    """A burst measured full chunks at an inflated cost (contention in the threads); afterwards only small chunks
    run. Their cost per window bounds the full chunks' from above, so the capacity the stream admission reads
    recovers instead of staying at the burst's figure."""

    async def main() -> tuple[float, float]:
        rec = _Recorder(0.004)  # 2 ms per window in chunks of 2
        batcher = MicroBatcher(rec, workers=1, chunk=8, max_wait_ms=0.0, spare=0)
        batcher.seconds_per_window = batcher.seconds_per_small_window = 0.004  # what the burst left: 4 ms per window
        before = batcher.capacity_windows_per_s
        batcher.start()
        for k in range(30):
            await batcher.infer(_windows(k, 2), 0.0)
        await batcher.stop()
        return before, batcher.capacity_windows_per_s

    before, after = asyncio.run(main())
    assert before == pytest.approx(250.0)
    assert after == pytest.approx(500.0, rel=0.05)


def test_a_capacity_set_by_the_operator_is_kept_whatever_the_chunks_cost() -> None:
    async def main() -> tuple[float | None, float | None]:
        rec = _Recorder(0.004)  # 2 ms per window in chunks of 2, 0.5 ms in full chunks of 8
        batcher = MicroBatcher(rec, workers=1, chunk=8, max_wait_ms=0.0, spare=0)
        batcher.set_capacity(100.0)
        batcher.start()
        for k in range(10):
            await batcher.infer(_windows(k, 2), 0.0)
            await batcher.infer(_windows(k, 8), 0.0)
        await batcher.stop()
        return batcher.capacity_windows_per_s, batcher.stream_capacity_windows_per_s

    assert asyncio.run(main()) == (pytest.approx(100.0), pytest.approx(100.0))


def test_the_stream_capacity_counts_the_workers_cpu_not_the_wall_time_a_burst_stretched() -> None:
    """Under another load's contention a chunk's wall time grows while its CPU time does not: the REST estimate
    (wall) sees the contention, the stream admission's capacity (CPU seconds of small chunks) does not keep it."""

    async def main() -> tuple[float | None, float | None]:
        rec = _Recorder(0.004, cpu_seconds=0.001)  # chunks of 2: 2 ms per window by the clock, 0.5 ms of CPU
        batcher = MicroBatcher(rec, workers=1, chunk=8, max_wait_ms=0.0, spare=0)
        await batcher.probe(lambda n: _windows(0, n))
        batcher.start()
        for k in range(10):
            await batcher.infer(_windows(k, 2), 0.0)
        await batcher.stop()
        return batcher.workers / batcher.seconds_per_small_window, batcher.stream_capacity_windows_per_s

    by_the_clock, streams = asyncio.run(main())
    assert by_the_clock == pytest.approx(500.0, rel=0.01)  # what a wall-time estimate would admit: 1 worker / 2 ms
    assert streams == pytest.approx(2000.0, rel=0.01)  # 1 worker / 0.5 ms of CPU
