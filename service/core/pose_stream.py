"""Live whole-body frames from several sensors' packets: the streaming twin of a pose request's sample rows.

Each sensor's packets carry consecutive samples from a sequence number; ``FrameAligner`` joins the sensors'
samples with the same number into one body frame ``(N, C)`` and releases every frame that all sensors have
reached. A gap is filled by holding the sensor's last sample (the pose model needs every frame; the fill is
reported) up to ``MAX_LAG_FRAMES``, a longer one ends the session; samples that repeat ones already received are
dropped and the rest of their packet kept (reported).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from service.core.stream import repeated_samples

MAX_LAG_FRAMES = 1200  # 20 s at 60 Hz: a sensor further behind the others stalls the session


class StreamLagError(ValueError):
    """One sensor is so far behind the others that their frames cannot be buffered any longer."""


@dataclass
class AlignResult:
    frames: np.ndarray  # (m, N, C), the frames all sensors have reached, oldest first
    first_frame: int  # index of frames[0] since the start of the stream
    filled: int = 0  # samples held to fill a gap in this packet
    late: tuple[int, int] | None = None  # (expected, received): the packet repeated samples already received
    late_dropped: int = 0  # its samples dropped: all of them, or the repeated ones before new ones (kept)
    notices: list[dict] = field(default_factory=list)


class FrameAligner:
    def __init__(self, n_sensors: int, width: int, names: list[str] | None = None) -> None:
        self.n, self.width = n_sensors, width
        self.names = names or [f"#{k}" for k in range(n_sensors)]  # how errors name the sensors
        self.buffers: list[list[np.ndarray]] = [[] for _ in range(n_sensors)]
        # plain ints: a live session pushes every packet through here, and numpy's per-call cost on N numbers is
        # larger than the work
        self.buffered = [0] * n_sensors
        self.expected = [0] * n_sensors
        self._none = np.zeros((0, n_sensors, width))
        self.last: list[np.ndarray | None] = [None] * n_sensors
        self.emitted = 0

    def push_all(self, seq: int, samples: np.ndarray) -> AlignResult | None:
        """Every sensor's samples ``(n, N, C)`` from ``seq`` at once (a frame packet): released as they are when
        every sensor is at ``seq`` with nothing buffered; None when they are not, and the packet must go through
        ``push`` sensor by sensor. A packet without samples changes nothing."""
        if not len(samples):
            return AlignResult(self._none, self.emitted)
        expected = self.expected[0]
        if any(self.buffered) or any(e != expected for e in self.expected) or seq < expected:
            return None
        filled = seq - expected  # every sensor skipped the same readings: hold each one's last sample
        if filled:
            self._check_gap(None, expected, seq)
            hold = np.stack([last if last is not None else samples[0, j] for j, last in enumerate(self.last)])
            samples = np.concatenate([np.repeat(hold[None], filled, axis=0), samples])
        self.expected = [seq + len(samples) - filled] * self.n
        self.last = list(samples[-1])
        result = AlignResult(samples, self.emitted, filled=filled)
        self.emitted += len(samples)
        return result

    def _check_gap(self, k: int | None, expected: int, seq: int) -> None:
        """A gap longer than ``MAX_LAG_FRAMES`` is refused before anything is held for it (a sequence number that
        jumps by millions must not fill memory with copies)."""
        if seq - expected > MAX_LAG_FRAMES:
            who = "every sensor" if k is None else f"sensor {self.names[k]}"
            raise StreamLagError(
                f"{who}: seq jumped from {expected} to {seq}, a gap of {seq - expected} samples; at most "
                f"{MAX_LAG_FRAMES} missing samples are filled (by holding the last one): start a new session"
            )

    def push(self, k: int, seq: int, samples: np.ndarray) -> AlignResult:
        """Add sensor ``k``'s ``samples`` ``(n, C)`` whose first has sequence number ``seq`` (none: nothing)."""
        result = AlignResult(self._none, self.emitted)
        if not len(samples):
            return result
        if seq < self.expected[k]:
            result.late = (self.expected[k], seq)
            result.late_dropped = repeated_samples(self.expected[k], seq, len(samples))
            if result.late_dropped == len(samples):
                return result
            samples, seq = samples[result.late_dropped :], self.expected[k]
        if seq > self.expected[k]:
            self._check_gap(k, self.expected[k], seq)
            hold = self.last[k] if self.last[k] is not None else samples[0]
            result.filled = seq - self.expected[k]
            self.buffers[k].append(np.repeat(hold[None], result.filled, axis=0))
            self.buffered[k] += result.filled
        self.buffers[k].append(samples)
        self.buffered[k] += len(samples)
        self.expected[k] = seq + len(samples)
        self.last[k] = samples[-1]
        most, m = max(self.buffered), min(self.buffered)
        if most - m > MAX_LAG_FRAMES:
            slow = self.buffered.index(m)
            raise StreamLagError(
                f"sensor {self.names[slow]} is {most - m} samples behind the others (at most {MAX_LAG_FRAMES})"
            )
        if m == 0:
            return result
        out = np.empty((m, self.n, self.width))
        for j in range(self.n):
            joined = np.concatenate(self.buffers[j]) if len(self.buffers[j]) > 1 else self.buffers[j][0]
            out[:, j] = joined[:m]
            rest = joined[m:]
            self.buffers[j] = [rest] if len(rest) else []
        self.buffered = [b - m for b in self.buffered]
        result.frames, result.first_frame = out, self.emitted
        self.emitted += m
        return result
