"""The streaming path equals the batch path: windows of a chunked stream = sliding_windows."""

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from service.core.stream import LinearResampler, SensorStream, resample_linear
from service.core.windowing import sliding_windows


def _chunks(x: np.ndarray, sizes: list[int]):
    i, k = 0, 0
    while i < len(x):
        n = sizes[k % len(sizes)]
        yield i, x[i : i + n]
        i += n
        k += 1


@given(st.lists(st.integers(1, 40), min_size=1, max_size=10))
@settings(max_examples=40, deadline=None)
def test_stream_windows_equal_batch_windows(sizes: list[int]) -> None:
    x = np.random.default_rng(0).normal(size=(400, 6)).astype(np.float32)
    stream = SensorStream("s", 60.0, "m/s^2", "rad/s")
    got = []
    for seq, chunk in _chunks(x, sizes):
        got += stream.push(seq, chunk).windows
    np.testing.assert_array_equal(np.stack(got), sliding_windows(x))


@given(st.sampled_from([50.0, 100.0, 204.8, 120.0]), st.lists(st.integers(1, 50), min_size=1, max_size=6))
@settings(max_examples=30, deadline=None)
def test_streaming_resampler_equals_batch_resampler(rate: float, sizes: list[int]) -> None:
    x = np.random.default_rng(1).normal(size=(500, 6))
    r = LinearResampler(rate)
    got = np.concatenate([r.push(c) for _, c in _chunks(x, sizes)])
    want = resample_linear(x, rate)
    n = min(len(got), len(want))
    assert abs(len(got) - len(want)) <= 1
    np.testing.assert_allclose(got[:n], want[:n], atol=1e-9)


def test_gap_restarts_the_window_and_late_packets_are_dropped() -> None:
    x = np.ones((200, 6), dtype=np.float32)
    stream = SensorStream("s", 60.0, "m/s^2", "rad/s")
    assert len(stream.push(0, x[:130]).windows) == 1
    gap = stream.push(140, x[:100])
    assert gap.gap == (130, 140) and gap.windows == []
    late = stream.push(100, x[:10])
    assert late.late == (240, 100) and late.windows == [] and late.late_dropped == 10
    assert len(stream.push(240, x[:28]).windows) == 1  # 128 contiguous samples since the gap


def test_a_packet_that_overlaps_keeps_its_new_samples() -> None:
    """A resent packet that overlaps what came (seq 110, 20 rows after 0-119): its 10 repeated samples are
    dropped, its 10 new ones go on the stream, and the next packet is no gap."""
    x = np.arange(200 * 6, dtype=np.float32).reshape(200, 6)
    stream = SensorStream("s", 60.0, "m/s^2", "rad/s")
    stream.push(0, x[:120])
    overlap = stream.push(110, x[110:130])
    assert overlap.late == (120, 110) and overlap.late_dropped == 10 and stream.expected_seq == 130
    after = stream.push(130, x[130:144])
    assert after.gap is None and len(after.windows) == 1
    np.testing.assert_array_equal(after.windows[0], x[16:144])  # one contiguous stream, nothing repeated
