"""Admission of live streams against the measured inference capacity.

A stream's demand is counted in windows per second of the I2S models (a 60 Hz sensor: one window per 16-sample
hop, 3.75 windows/s, whatever rate it is sent at, since it is resampled to 60 Hz). Pose and flex sessions run
other models; their demand is converted to the same unit through their models' measured seconds per frame and
the I2S streams' seconds per window (``MicroBatcher.stream_seconds_per_window``: CPU seconds in chunks of 2 windows,
the unit the stream capacity is counted in). Live pose and live flex sessions run in batches
(``service.inference.session_batcher``), whose cost is a fixed part per batch plus a part per frame: the part per
frame is what one more session adds, measured at start-up with batches of one and of many sessions
(``SessionBatcher.probe``), as the I2S capacity is, on an idle machine. A pose model's is not updated from the
batches under load: their times in the worker thread grow with the event loop's share of the interpreter (three to
four times on two cores), while the I2S CPU seconds per window they are compared with do not. A flex model's is
refined under load (an EWMA of its batches' seconds beyond their fixed part, over their frames): with the probe's
figure alone a burst of 50 suits all got in, at p99 96-187 ms (flex.md, Speed).

A new stream is refused (close code 1013, "try again later") while the event loop is behind: when a timer that
should fire every ``LAG_TICK_S`` fired more than ``latency_target_ms`` × ``LAG_SHARE`` late at the 90th percentile
of the last ``LAG_WINDOW_S`` seconds. Reading the streams' packets is the event loop's work, and a packet that waits
in the socket for a busy loop is not seen by the answer latencies below (they start when the packet is read). It
is refused too when its demand would take the admitted streams' total past ``fraction`` × capacity: beyond it
every admitted stream's answers would fall behind, as they did when 51 sensors on a 26-sensor machine all got
answers 8–50 s late. It is refused too while the admitted streams'
answers are already late: when the p99 of their packet-to-answer times over the last ``WINDOW_S`` seconds passes
``latency_target_ms`` (the capacity estimate does not see the event loop's own work for many streams, nor other
programs on the machine).
"""

from __future__ import annotations

import asyncio
import itertools
import time
from collections import deque
from collections.abc import Callable
from typing import Any

import numpy as np

from service.api.protocol import ProtocolError
from service.inference.batcher import MicroBatcher
from service.inference.pose_batcher import LivePoseBatcher

I2S_WINDOWS_PER_SENSOR_S = 60.0 / 16  # model rate / hop
WINDOW_S = 10.0  # of recent answer latencies
MIN_LATENCIES = 50  # fewer than this in the window: too few to judge
LAG_TICK_S = 0.02  # the event-loop lag timer's period
LAG_WINDOW_S = 2.0  # of recent lag measurements
LAG_SHARE = 0.25  # of the latency target: the loop lag (p90) beyond which new streams are refused
EWMA_WEIGHT = 0.2  # of a live flex batch's cost per frame
RISING_WINDOW_S = 1.0  # of the most recent answer latencies: a load that is still rising
RISING_SHARE = 0.35  # of the latency target: their p99 beyond which new pose or flex sessions are refused


class StreamAdmission:
    def __init__(self, fraction: float, latency_target_ms: float = 100.0, pose_busy_limit: float = 0.8) -> None:
        self.fraction = fraction
        self.pose_busy_limit = pose_busy_limit
        self.latency_target_ms = latency_target_ms
        # (monotonic time, seconds); one per answered packet: 16,384 hold the last 10 s of 100 pose suits at 15
        # packets/s, 4,096 the last second of 270
        self.latencies: deque[tuple[float, float]] = deque(maxlen=16384)
        self.pose_latencies: deque[tuple[float, float]] = deque(maxlen=4096)  # the live pose answers' alone
        self.flex_latencies: deque[tuple[float, float]] = deque(maxlen=4096)  # the live flex answers' alone
        self.demand: dict[int, float] = {}  # session → windows/s
        # flex model name, or live pose session's cost key (``LivePose.cost_key``) → seconds per frame (one worker)
        self.seconds_per_frame: dict[str, float] = {}
        self.ids = itertools.count()
        self.lags: deque[tuple[float, float]] = deque(maxlen=1024)  # (monotonic time, seconds late)
        self.loop_cpu: deque[tuple[float, float]] = deque(maxlen=1024)  # (monotonic time, loop thread's CPU s)

    async def watch_loop(self) -> None:
        """Measure how late the event loop runs a timer, for as long as the service runs."""
        while True:
            due = time.monotonic() + LAG_TICK_S
            await asyncio.sleep(LAG_TICK_S)
            now = time.monotonic()
            self.lags.append((now, max(now - due, 0.0)))
            self.loop_cpu.append((now, time.thread_time()))

    def loop_busy_share(self) -> float | None:
        """The share of the last ``LAG_WINDOW_S`` the event loop's thread spent on the CPU (reading and answering
        every stream's packets, HTTP, JSON); None before it has run."""
        since = time.monotonic() - LAG_WINDOW_S
        recent = [(t, cpu) for t, cpu in self.loop_cpu if t >= since]
        if len(recent) < 10:
            return None
        (t0, cpu0), (t1, cpu1) = recent[0], recent[-1]
        return (cpu1 - cpu0) / (t1 - t0)

    def loop_lag_ms(self) -> float | None:
        """p90 of how late the loop ran its timer over the last ``LAG_WINDOW_S``; None before it has run."""
        since = time.monotonic() - LAG_WINDOW_S
        recent = [lag for t, lag in self.lags if t >= since]
        return 1000 * float(np.percentile(recent, 90)) if len(recent) >= 10 else None

    @property
    def total(self) -> float:
        return sum(self.demand.values())

    def model_demand(self, batcher: MicroBatcher, model: str, frames_per_s: float) -> float:
        """Windows/s equivalent of running ``model`` on ``frames_per_s`` (0 until the model has been measured)."""
        spw = batcher.stream_seconds_per_window
        cost = self.seconds_per_frame.get(model)
        return 0.0 if not spw or cost is None else frames_per_s * cost / spw

    def observe(self, model: str, frames: int, seconds: float) -> None:
        """A live flex batch's part per frame took ``seconds`` for ``frames`` frames (EWMA from the probe's value)."""
        if frames <= 0:
            return
        per_frame = seconds / frames
        old = self.seconds_per_frame.get(model)
        self.seconds_per_frame[model] = per_frame if old is None else (1 - EWMA_WEIGHT) * old + EWMA_WEIGHT * per_frame

    def set_frame_cost(self, model: str, per_frame_s: float) -> None:
        """A live pose or flex model's seconds per frame, measured by its start-up probe (one more session's cost)."""
        self.seconds_per_frame[model] = per_frame_s

    def observe_latency(self, seconds: float, pose: bool = False, flex: bool = False) -> None:
        """A stream packet's answers (live pose answers: ``pose``; live flex answers: ``flex``) were queued
        ``seconds`` after it arrived."""
        self.latencies.append((time.monotonic(), seconds))
        if pose:
            self.pose_latencies.append(self.latencies[-1])
        if flex:
            self.flex_latencies.append(self.latencies[-1])

    def recent_p99_ms(self, window_s: float = WINDOW_S, pose: bool = False, flex: bool = False) -> float | None:
        """p99 of the admitted streams' answer latencies (of live pose or flex answers only: ``pose``, ``flex``) of
        the last ``window_s``; None without enough of them (or streams)."""
        if not self.demand:
            self.latencies.clear()  # no stream is open: what was measured is over
            self.pose_latencies.clear()
            self.flex_latencies.clear()
            return None
        since = time.monotonic() - window_s
        kept = self.pose_latencies if pose else self.flex_latencies if flex else self.latencies
        recent = [s for t, s in kept if t >= since]
        return None if len(recent) < MIN_LATENCIES else 1000 * float(np.percentile(recent, 99))

    def pose_refusal(self, pose_batcher: LivePoseBatcher) -> str:
        """Why a new live pose session is refused ("" if its pose part may start; ``admit`` still judges its
        demand like any stream's):

        - while the load still rises: the live pose answers of the last second take more than ``RISING_SHARE`` of
          the target at p99. They take a few batch times (tens of ms) until the machine saturates, and then climb
          within a second; clients that arrive in a burst would otherwise all get in before the slower p99 of
          ``admit`` sees it. (I2S answers wait for company in their micro-batches by design: neither their
          latencies count here nor does this refuse I2S sessions.)
        - when the pose worker's busy share, projected with the sessions opened since and this one
          (``LivePoseBatcher.projected_busy_share``), passes ``pose_busy_limit``."""
        rising = self._rising("pose")
        if rising:
            return rising
        projected = pose_batcher.projected_busy_share()
        if projected > self.pose_busy_limit:
            return (
                f"at capacity: the live pose sessions keep their worker busy {100 * pose_batcher.busy_share():.0f} % "
                f"of the time, {100 * projected:.0f} % with this one (at most {100 * self.pose_busy_limit:.0f} %); "
                "try again later"
            )
        return ""

    def flex_refusal(self) -> str:
        """Why a new live flex session is refused while the load still rises ("" if not; ``admit`` still judges its
        demand): the live flex answers of the last second take more than ``RISING_SHARE`` of the target at p99, as
        for pose sessions (``pose_refusal``). The flex model's cost is probed on an idle machine; under load the
        event loop and the clients take their share of the same cores, which only the answers' latency shows."""
        return self._rising("flex")

    def _rising(self, kind: str) -> str:
        """The refusal of a new ``kind`` ("pose" or "flex") session while that kind's live answers of the last second
        take more than ``RISING_SHARE`` of the target at p99, else ""."""
        rising = self.recent_p99_ms(RISING_WINDOW_S, pose=kind == "pose", flex=kind == "flex")
        if rising is None or rising <= RISING_SHARE * self.latency_target_ms:
            return ""
        return (
            f"at capacity: the live {kind} answers of the last second take {rising:.0f} ms at p99 (at most "
            f"{RISING_SHARE * self.latency_target_ms:.0f} ms for a new {kind} session); try again later"
        )

    def admit(self, batcher: MicroBatcher, windows_per_s: float) -> tuple[int | None, str]:
        """(a session key, "") if admitted, else (None, why)."""
        lag = self.loop_lag_ms()
        if lag is not None and lag > LAG_SHARE * self.latency_target_ms:
            return None, (
                f"at capacity: the service's event loop runs {lag:.0f} ms late (at most "
                f"{LAG_SHARE * self.latency_target_ms:.0f} ms); try again later"
            )
        p99 = self.recent_p99_ms()
        if p99 is not None and p99 > self.latency_target_ms:
            return None, (
                f"at capacity: the admitted streams' answers take {p99:.0f} ms at p99 (target "
                f"{self.latency_target_ms:.0f} ms); try again later"
            )
        capacity = batcher.stream_capacity_windows_per_s
        limit = None if capacity is None else self.fraction * capacity
        if limit is not None and self.total + windows_per_s > limit:
            return None, (
                f"at capacity: this stream needs {windows_per_s:.1f} windows/s, the admitted streams take "
                f"{self.total:.1f} of {limit:.1f} windows/s; try again later"
            )
        key = next(self.ids)
        self.demand[key] = windows_per_s
        return key, ""

    def release(self, key: int | None) -> None:
        if key is not None:
            self.demand.pop(key, None)


def flex_batch_observer(
    streams: StreamAdmission, fixed_s: Callable[[str], float]
) -> Callable[[str, list[tuple], float], None]:
    """The ``on_batch`` of the live flex batches: a batch's seconds beyond its fixed part (``fixed_s(model)``, the
    start-up probe's) over its sessions' model-rate frames: what one more session adds, as the load makes it."""

    def observe(model: str, calls: list[tuple], seconds: float) -> None:
        frames = sum(len(rows) // live.factor for live, rows in calls)
        streams.observe(model, frames, max(seconds - fixed_s(model), 0.0))

    return observe


def admit_or_refuse(app: Any, windows_per_s: float) -> int:
    """Admit a session of this demand (its key) or raise ``ProtocolError`` 1013 with the reason; counted in
    ``/metrics``."""
    key, why = app.state.streams.admit(app.state.batcher, windows_per_s)
    if key is None:
        app.state.metrics.streams_refused.labels("capacity").inc()
        raise ProtocolError(why, 1013)
    app.state.metrics.streams_admitted.inc()
    return key


def record_answer_latency(app: Any, seconds: float, pose: bool = False, flex: bool = False) -> None:
    """A stream packet's answers (live pose answers: ``pose``; live flex answers: ``flex``) were queued ``seconds``
    after it arrived: for ``/metrics`` and for admission."""
    app.state.metrics.stream_result.observe(seconds)
    app.state.streams.observe_latency(seconds, pose, flex)
