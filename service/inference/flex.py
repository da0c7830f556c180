"""Running a ``flex_pose`` model (Chen et al. 2024): raw readings → joint angles per sample, offline over a block
or live over a stream, with the model's calibration window of the last ``window_samples`` readings."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from service.core.flex import FlexWindow, ReadoutCheck, ReadoutFailure, answer_mask, block_windows
from service.core.resample import resample_uniform
from service.inference.predict import InputError
from service.inference.registry import LoadedModel

MIN_FLEX_RATE_HZ, MAX_FLEX_RATE_HZ = 1.0, 2000.0
MAX_FLEX_SAMPLES = 36_000  # per REST block at the model's rate: 30 minutes at 20 Hz
CHUNK_WINDOWS = 2048  # windows per onnxruntime call: a long block never holds all its windows at once


@dataclass
class FlexModel:
    loaded: LoadedModel

    def __post_init__(self) -> None:
        m = self.loaded.manifest
        if m.task != "flex_pose" or m.flex is None:
            raise ValueError(f"{m.name} is not a flex_pose model")
        # a model in the hinge frames answers what they hold at zero as zero (service.core.flex.HINGE_ZEROS)
        self.answer_mask = answer_mask(m.training_data.get("limb_twist"), m.joints, m.joint_components)

    @property
    def name(self) -> str:
        return self.loaded.manifest.name

    @property
    def manifest(self):
        return self.loaded.manifest

    @property
    def window(self) -> int:
        return self.manifest.window_samples

    @property
    def latency(self) -> int:
        return self.manifest.flex.latency_samples

    def readout_check(self, rate_hz: float) -> ReadoutCheck | None:
        """A fresh read-out failure check for readings at ``rate_hz``, if the manifest declares one."""
        spec = self.manifest.flex.readout_check
        return None if spec is None else ReadoutCheck(rate_hz, spec.reference_s, spec.max_deviation)

    def run_windows(self, windows: np.ndarray) -> np.ndarray:
        """``(n, window, C)`` → ``(n, joints, components)`` degrees, as the service answers them (``answer_mask``)."""
        out = [
            self.loaded.run(np.ascontiguousarray(windows[i : i + CHUNK_WINDOWS], np.float32))
            for i in range(0, len(windows), CHUNK_WINDOWS)
        ]
        if not out:
            return np.zeros((0, len(self.manifest.joints), len(self.manifest.joint_components)))
        angles = np.concatenate(out)
        return angles if self.answer_mask is None else np.where(self.answer_mask == 0.0, 0.0, angles)  # no −0.0

    def run_block(self, rows: np.ndarray) -> np.ndarray:
        """Rows ``(T, C)`` at the model's rate, ``T >= window`` → angles of samples ``window - 1 - latency`` to
        ``T - 1 - latency``: one answer per sample once the calibration window is full."""
        out = []
        step = CHUNK_WINDOWS
        for start in range(self.window, len(rows) + 1, step):
            stop = min(len(rows), start + step - 1)
            out.append(self.run_windows(block_windows(rows[start - self.window : stop], self.window)))
        return np.concatenate(out)


def check_rows(x: np.ndarray, model: FlexModel, where: str) -> None:
    """Finite values inside the manifest's value range, ``C`` per row; else an ``InputError`` naming the row."""
    m = model.manifest
    if x.ndim != 2 or x.shape[1] != len(m.channels):
        got = x.shape[1] if x.ndim == 2 else "ragged rows"
        raise InputError(f"{where}: every sample needs {len(m.channels)} values ({', '.join(m.channels)}), got {got}")
    finite = np.isfinite(x).all(axis=1)
    if not finite.all():
        raise InputError(f"{where}[{int(np.argmin(finite))}]: samples must be finite numbers, got NaN or Inf")
    if m.value_range is not None:
        lo, hi = m.value_range
        bad = ((x < lo) | (x > hi)).any(axis=1)
        if bad.any():
            i = int(np.argmax(bad))
            unit = m.units.get(m.channels[0])
            raise InputError(
                f"{where}[{i}]: values must lie in [{lo:g}, {hi:g}]{f' ({unit})' if unit else ''}, "
                f"got {[round(v, 3) for v in x[i].tolist()]}"
            )


# Every reading of a block at most this, for a model whose range reaches into the thousands (12-bit counts), reads
# as volts or values scaled to 0–1: a 3.3 V read-out gives 0–3.3 V, the model takes its ADC's counts.
SMALL_READING = 5.0


def reading_warnings(x: np.ndarray, model: FlexModel) -> list[str]:
    """Warnings for rows ``(T, C)`` as the client sent them (before any resampling) that pass ``check_rows`` but read
    like a mistake: every value small where the model takes counts in the thousands (volts or 0–1 values sent as
    counts), or a channel that reads one value over all the rows, at least a calibration window's worth (a
    disconnected, shorted or saturated sensor; at the range's end, the ADC's limit). The angles are answered; the
    warnings say why they may be wrong."""
    m = model.manifest
    out: list[str] = []
    if not x.size:
        return out
    peak = float(np.abs(x).max())
    if m.value_range is not None and m.value_range[1] >= 1000.0 and peak <= SMALL_READING:
        unit = m.units.get(m.channels[0]) or f"values in [{m.value_range[0]:g}, {m.value_range[1]:g}]"
        out.append(f"every reading is at most {peak:.3g}, where the model takes {unit}: are they volts or 0–1 values?")
    if len(x) >= model.window:
        for c in np.flatnonzero(np.ptp(x, axis=0) == 0.0):
            value = float(x[0, c])
            limit = " (the end of the value range: the read-out's limit)" if value in (m.value_range or ()) else ""
            out.append(
                f"channel {m.channels[c]} reads {value:g}{limit} in all {len(x)} samples: a disconnected, shorted or "
                f"saturated sensor reads so, and its joints' angles are guesses"
            )
    return out


def readout_message(failure: ReadoutFailure, model: FlexModel, where: str) -> str:
    """What a client is told when its sensor's read-out fails: where, which channel, what it read and expected."""
    spec = model.manifest.flex.readout_check
    return (
        f"{where}: channel {model.manifest.channels[failure.channel]} read {failure.value:.6g} where its first "
        f"{spec.reference_s:g} s read {failure.reference:.6g} (median): more than {spec.max_deviation:.0%} off, so "
        f"the sensor's read-out has failed (a loose connection or a failing board reads so); the readings before "
        f"it are answered, none from it on"
    )


def block_rows(
    samples: list[list[float]], rate_hz: float | None, model: FlexModel, max_samples: int
) -> tuple[np.ndarray, list[str]]:
    """A REST block → rows at the model's rate, validated (it must cover the calibration window), and the
    ``reading_warnings`` of the rows as sent (resampling would blur a channel that never changes)."""
    m = model.manifest
    width = len(m.channels)
    bad = next((k for k, r in enumerate(samples) if len(r) != width), None)
    if bad is not None:
        raise InputError(
            f"samples[{bad}]: every sample needs {width} values ({', '.join(m.channels)}), got {len(samples[bad])}"
        )
    rate = m.sample_rate_hz if rate_hz is None else rate_hz
    if not MIN_FLEX_RATE_HZ <= rate <= MAX_FLEX_RATE_HZ:
        raise InputError(f"sample_rate_hz must be in [{MIN_FLEX_RATE_HZ:g}, {MAX_FLEX_RATE_HZ:g}], got {rate:g}")
    n_model = int(round(len(samples) * m.sample_rate_hz / rate))
    if n_model > max_samples:
        raise InputError(
            f"samples: at most {max_samples} samples at {m.sample_rate_hz:g} Hz per request, got {len(samples)} "
            f"at {rate:g} Hz, {n_model} at {m.sample_rate_hz:g} Hz; send longer recordings in blocks or over "
            "/v1/stream/flex"
        )
    x = np.asarray(samples, dtype=np.float64)
    check_rows(x, model, "samples")
    readout = model.readout_check(rate)
    failure = None if readout is None else readout.first_failure(x)
    if failure is not None:
        raise InputError(
            readout_message(failure, model, f"samples[{failure.row}]")
            + f" (send samples[:{failure.row}] for the angles before it)"
        )
    warnings = reading_warnings(x, model)
    if not np.isclose(rate, m.sample_rate_hz):
        x = resample_uniform(x, rate, m.sample_rate_hz)
    if len(x) < model.window:
        need = int(np.ceil(model.window * rate / m.sample_rate_hz))
        raise InputError(
            f"samples: a block must cover the calibration window of {model.window} samples at "
            f"{m.sample_rate_hz:g} Hz ({model.window / m.sample_rate_hz:g} s), i.e. at least {need} samples at "
            f"{rate:g} Hz; got {len(samples)}"
        )
    return x.astype(np.float32), warnings


class LiveFlex:
    """One stream's state: the calibration window and the decimation from the stream's rate (an integer multiple
    of the model's: each ``factor`` readings are averaged into one)."""

    def __init__(self, model: FlexModel, factor: int) -> None:
        self.model = model
        self.factor = factor
        self.buffer = FlexWindow(model.window, len(model.manifest.channels))
        self._pending = np.zeros((0, len(model.manifest.channels)))
        self.samples_in = 0  # readings accepted, at the stream's rate
        self.model_samples = 0  # samples pushed into the window, at the model's rate
        self.readout = model.readout_check(model.manifest.sample_rate_hz * factor)  # one reference per stream
        self._first: list[np.ndarray] | None = []  # the first window's readings, until ``first_window_warnings``
        self._first_rows = 0

    def first_window_warnings(self, rows: np.ndarray) -> list[str]:
        """``reading_warnings`` once, over the stream's first calibration window of readings (at the stream's
        rate); empty before and after."""
        if self._first is None:
            return []
        self._first.append(rows)
        self._first_rows += len(rows)
        if self._first_rows < self.model.window * self.factor:
            return []
        first, self._first = np.concatenate(self._first), None
        return reading_warnings(first, self.model)

    def take(self, rows: np.ndarray) -> tuple[int, np.ndarray]:
        """Accept readings at the stream's rate → (model-rate index of the first answer, the model inputs they
        complete ``(n, window, C)``)."""
        self.samples_in += len(rows)
        rows = np.concatenate([self._pending, rows])
        usable = len(rows) // self.factor * self.factor
        self._pending = rows[usable:]
        reduced = rows[:usable].reshape(-1, self.factor, rows.shape[1]).mean(axis=1)
        windows = self.buffer.push(reduced)
        first = self.model_samples + len(reduced) - len(windows) - self.model.latency
        self.model_samples += len(reduced)
        shape = (len(windows), self.model.window, len(self.model.manifest.channels))
        return first, np.stack(windows) if windows else np.zeros(shape, np.float32)

    def push(self, rows: np.ndarray) -> tuple[int, np.ndarray]:
        """Accept readings at the stream's rate → (model-rate index of the first answer, answers ``(n, J, K)``)."""
        return process_live_flex([(self, rows)])[0]

    def jump_to(self, seq: int) -> None:
        """After a gap up to reading ``seq``: the window starts again (its calibration would mix readings from
        before and after); sample indices keep counting the stream's time."""
        self.buffer = FlexWindow(self.model.window, len(self.model.manifest.channels))
        self._pending = self._pending[:0]
        self.samples_in = seq
        self.model_samples = seq // self.factor


def process_live_flex(jobs: list[tuple[LiveFlex, np.ndarray]]) -> list[tuple[int, np.ndarray]]:
    """New readings of several live sessions of one model → each session's (first answered sample, answers), with
    one network call for the windows of all of them (``service.inference.session_batcher``): each window is
    answered as it would be alone."""
    taken = [live.take(rows) for live, rows in jobs]
    model = jobs[0][0].model
    windows = [w for _, w in taken if len(w)]
    out = model.run_windows(np.concatenate(windows)) if windows else None
    answers, at = [], 0
    for first, w in taken:
        answers.append((first, out[at : at + len(w)] if len(w) else model.run_windows(w)))
        at += len(w)
    return answers


def probe_sessions(model: FlexModel, sessions: int, packet: int) -> Callable[[int], list[tuple]]:
    """``calls_for`` of ``SessionBatcher.probe`` for a flex model: sessions whose calibration window is full (a
    still sensor in the middle of the model's value range), ``packet`` readings each."""
    lo, hi = model.manifest.value_range or (1000.0, 1000.0)
    still = np.full((model.window - 1, len(model.manifest.channels)), (lo + hi) / 2)
    lives = [LiveFlex(model, 1) for _ in range(sessions)]
    for live in lives:
        live.take(still)
    return lambda n: [(live, still[:packet]) for live in lives[:n]]
