"""Body frames from several sensors' packets: released when every sensor has them, gaps held, late dropped."""

from __future__ import annotations

import numpy as np
import pytest

from service.core.pose_stream import MAX_LAG_FRAMES, FrameAligner, StreamLagError


def _rows(start: int, n: int, sensor: int) -> np.ndarray:
    return np.stack([np.full(3, 100 * sensor + start + i, dtype=np.float64) for i in range(n)])


def test_frames_are_released_once_every_sensor_has_them_in_any_packet_sizes() -> None:
    a = FrameAligner(2, 3)
    assert len(a.push(0, 0, _rows(0, 5, 0)).frames) == 0
    out = a.push(1, 0, _rows(0, 3, 1))
    assert out.first_frame == 0 and out.frames.shape == (3, 2, 3)
    np.testing.assert_array_equal(out.frames[:, 1, 0], [100, 101, 102])
    out = a.push(1, 3, _rows(3, 4, 1))
    assert out.first_frame == 3 and len(out.frames) == 2  # sensor 0 has only reached frame 4
    np.testing.assert_array_equal(out.frames[:, 0, 0], [3, 4])


def test_a_gap_holds_the_last_sample_and_a_late_packet_is_dropped() -> None:
    a = FrameAligner(1, 3)
    a.push(0, 0, _rows(0, 2, 0))
    out = a.push(0, 5, _rows(5, 1, 0))
    assert out.filled == 3
    np.testing.assert_array_equal(out.frames[:, 0, 0], [1, 1, 1, 5])
    late = a.push(0, 2, _rows(2, 2, 0))
    assert late.late == (6, 2) and len(late.frames) == 0 and late.late_dropped == 2
    overlap = a.push(0, 4, _rows(4, 4, 0))  # samples 4, 5 repeat; 6, 7 are new
    assert overlap.late == (6, 4) and overlap.late_dropped == 2 and overlap.filled == 0
    np.testing.assert_array_equal(overlap.frames[:, 0, 0], [6, 7])


def test_a_sensor_that_falls_far_behind_stops_the_session() -> None:
    a = FrameAligner(2, 3)
    with pytest.raises(StreamLagError, match="sensor #1"):
        a.push(0, 0, _rows(0, MAX_LAG_FRAMES + 1, 0))
    named = FrameAligner(2, 3, ["pelvis", "shank"])
    with pytest.raises(StreamLagError, match="sensor shank is"):
        named.push(0, 0, _rows(0, MAX_LAG_FRAMES + 1, 0))


@pytest.mark.parametrize("seq", [MAX_LAG_FRAMES + 3, 40_000_000, 2**32 - 1, 10**20])
def test_a_gap_too_long_to_fill_is_refused_before_anything_is_held(seq: int) -> None:
    """A sequence number that jumps by millions (a device counting from a timestamp) must not fill memory with
    held copies: the gap is refused, naming the sensor and the jump, and nothing is buffered."""
    a = FrameAligner(2, 3, ["pelvis", "shank"])
    a.push(1, 0, _rows(0, 2, 1))
    with pytest.raises(StreamLagError, match=f"sensor shank: seq jumped from 2 to {seq}"):
        a.push(1, seq, _rows(0, 1, 1))
    assert a.buffered == [0, 2]
    with pytest.raises(StreamLagError, match=f"every sensor: seq jumped from 0 to {seq}"):
        FrameAligner(2, 3).push_all(seq, np.zeros((1, 2, 3)))


def test_a_frame_packet_after_a_gap_holds_every_sensor_alike() -> None:
    """Every sensor skipped the same readings (a frame packet after a gap): each holds its own last sample and the
    frames are released at once; a gap as long as the buffer allows is not mistaken for a sensor falling behind."""
    a = FrameAligner(2, 3)
    first = np.stack([_rows(0, 2, 0), _rows(0, 2, 1)], axis=1)
    assert len(a.push_all(0, first).frames) == 2
    gap = MAX_LAG_FRAMES
    out = a.push_all(2 + gap, np.stack([_rows(500, 30, 0), _rows(500, 30, 1)], axis=1))
    assert out.filled == gap and out.first_frame == 2 and out.frames.shape == (gap + 30, 2, 3)
    np.testing.assert_array_equal(out.frames[:gap, 0, 0], 1)  # sensor 0's last sample, held
    np.testing.assert_array_equal(out.frames[:gap, 1, 0], 101)
    np.testing.assert_array_equal(out.frames[gap:, 1, 0], np.arange(600, 630))
    assert a.expected == [2 + gap + 30] * 2


def test_a_packet_without_samples_changes_nothing() -> None:
    """A binary packet may carry n = 0 samples (the header allows it): nothing is released, held or reported."""
    a = FrameAligner(2, 3)
    a.push(0, 0, _rows(0, 2, 0))
    empty = a.push(1, 0, np.zeros((0, 3)))
    assert len(empty.frames) == 0 and empty.filled == 0 and empty.late is None
    assert a.push_all(0, np.zeros((0, 2, 3))) is not None and len(a.push_all(0, np.zeros((0, 2, 3))).frames) == 0
    out = a.push(1, 0, _rows(0, 2, 1))
    assert out.first_frame == 0 and len(out.frames) == 2  # as if the empty packets had never come
    fresh = FrameAligner(2, 3)
    assert len(fresh.push_all(0, np.zeros((0, 2, 3))).frames) == 0
    assert len(fresh.push_all(0, np.stack([_rows(0, 2, 0), _rows(0, 2, 1)], axis=1)).frames) == 2
