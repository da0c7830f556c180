"""Per-sensor streaming state: sequence checking, resampling to 60 Hz and a 128-sample ring buffer
that releases a window every 16 new samples — the streaming twin of ``sliding_windows``.

Gaps (a packet starts after the expected sequence number) and reordering or duplicates (it starts
before) are never merged silently: a gap restarts the window (windows must be contiguous) and is
reported; a late packet is dropped and reported.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from service.core.resample import resample_timestamps
from service.core.units import to_contract_units
from service.core.windowing import HOP_SAMPLES, MODEL_RATE_HZ, WINDOW_SAMPLES


class LinearResampler:
    """Streaming linear interpolation from ``from_hz`` onto the 60 Hz grid (same result however the
    stream is chunked; equals ``resample_linear`` on the whole stream)."""

    def __init__(self, from_hz: float, to_hz: float = MODEL_RATE_HZ) -> None:
        self.step = from_hz / to_hz  # input samples per output sample
        self.next_pos = 0.0  # position of the next output sample, in input samples from the start
        self.offset = 0  # input samples consumed before ``self.last``
        self.last: np.ndarray | None = None  # last input sample, kept to interpolate across chunks

    def push(self, x: np.ndarray) -> np.ndarray:
        if self.step == 1.0:
            return x
        if self.last is not None:
            x = np.concatenate([self.last[None], x])
            base = self.offset - 1
        else:
            base = self.offset
        end = base + len(x) - 1  # position of the newest input sample
        positions = np.arange(self.next_pos, end + 1e-9, self.step)
        rel = positions - base
        i0 = np.floor(rel).astype(np.int64)
        i1 = np.minimum(i0 + 1, len(x) - 1)
        w = (rel - i0)[:, None]
        out = (1 - w) * x[i0] + w * x[i1]
        self.next_pos = positions[-1] + self.step if len(positions) else self.next_pos
        self.offset = end + 1
        self.last = x[-1]
        return out


def resample_linear(x: np.ndarray, from_hz: float, to_hz: float = MODEL_RATE_HZ) -> np.ndarray:
    """Batch form of ``LinearResampler``: samples at t = k / to_hz for all k within the stream."""
    if from_hz == to_hz:
        return x
    return resample_timestamps(np.arange(len(x)) / from_hz, x, to_hz)[1]


def repeated_samples(expected_seq: int, seq: int, n: int) -> int:
    """How many of a packet's ``n`` samples from ``seq`` repeat samples already received (``expected_seq``: the
    next new one): dropped, and the packet's samples after them kept."""
    return max(0, min(expected_seq - seq, n))


@dataclass
class PushResult:
    windows: list[np.ndarray] = field(default_factory=list)  # each (128, 6) float32, contract units
    window_end_s: list[float] = field(default_factory=list)  # sensor-clock time of each window's last sample
    gap: tuple[int, int] | None = None  # (expected, received): the window restarts at the new packet
    late: tuple[int, int] | None = None  # (expected, received): the packet repeated samples already received
    late_dropped: int = 0  # its samples dropped: all of them, or the repeated ones before new ones (kept)


class SensorStream:
    """One sensor's stream: windows start at model-rate samples 0, 16, 32, … after each (re)start,
    exactly as ``sliding_windows`` cuts a recording."""

    def __init__(self, sensor_id: str, sample_rate_hz: float, acc_unit: str, gyr_unit: str) -> None:
        self.sensor_id = sensor_id
        self.sample_rate_hz = sample_rate_hz
        self.acc_unit, self.gyr_unit = acc_unit, gyr_unit
        self.expected_seq = 0
        self.samples_received = 0
        self._restart(0)

    def _restart(self, seq: int) -> None:
        self.resampler = LinearResampler(self.sample_rate_hz)
        self.history = np.zeros((0, 6), dtype=np.float32)  # the newest model-rate samples (< 128 kept)
        self.count = 0  # model-rate samples since the (re)start
        self.start_s = seq / self.sample_rate_hz

    def push(self, seq: int, samples: np.ndarray) -> PushResult:
        """Add ``samples`` ``(N, 6)`` (declared units) whose first has sequence number ``seq``."""
        result = PushResult()
        if seq < self.expected_seq:
            result.late = (self.expected_seq, seq)
            result.late_dropped = repeated_samples(self.expected_seq, seq, len(samples))
            if result.late_dropped == len(samples):
                return result
            samples, seq = samples[result.late_dropped :], self.expected_seq
        if seq > self.expected_seq:
            result.gap = (self.expected_seq, seq)
            self._restart(seq)
        self.expected_seq = seq + len(samples)
        self.samples_received += len(samples)
        x = self.resampler.push(to_contract_units(samples, self.acc_unit, self.gyr_unit)).astype(np.float32)
        first = self.count - len(self.history)  # model-rate index of history[0]
        history = np.concatenate([self.history, x])
        for end in range(self.count, self.count + len(x)):
            if end >= WINDOW_SAMPLES - 1 and (end - WINDOW_SAMPLES + 1) % HOP_SAMPLES == 0:
                lo = end - WINDOW_SAMPLES + 1 - first
                result.windows.append(history[lo : lo + WINDOW_SAMPLES].copy())
                result.window_end_s.append(self.start_s + end / MODEL_RATE_HZ)
        self.count += len(x)
        self.history = history[-(WINDOW_SAMPLES - 1) :]
        return result
