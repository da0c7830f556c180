"""One sensor's CSV file with its columns mapped onto acc x, y, z and gyr x, y, z: a layout by position or by
header name, and presets for the exports of common IMUs (x-IMU3 ``Inertial.csv``, Movella DOT CSV, Xsens MT
Manager text), which also name the units and where the file keeps its time.

A file without a layout is read by ``service.core.recordings.read_csv_imu`` (acc then gyr, after skipped
columns); this module is for everything else.
"""

from __future__ import annotations

import gzip
import re
from collections.abc import Sequence
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from service.core.resample import resample_timestamps

CHANNELS: tuple[str, ...] = ("acc_x", "acc_y", "acc_z", "gyr_x", "gyr_y", "gyr_z")
TIME_LABELS = {"time_s": 1.0, "time_ms": 1e-3, "time_us": 1e-6}  # a time column by position, and its unit
IGNORED = "-"  # a column by position that holds something else
DELIMITERS = (",", "\t", ";")
GAP_FACTOR = 1.5  # a step between timestamps beyond this many times the median is a gap (dropped samples)


class ColumnError(ValueError):
    """A layout that does not fit the file, or that cannot be read; the message says what was expected."""


@dataclass(frozen=True)
class CsvLayout:
    """Where a file's six readings are: ``channels`` gives acc x, y, z, gyr x, y, z in this order, each a header
    name or a 0-based column position; ``time`` likewise (None: the file keeps no time)."""

    name: str
    channels: tuple[str, ...] | tuple[int, ...]
    time: str | int | None = None
    time_scale_s: float = 1.0  # seconds per unit of the time column
    time_wrap: float | None = None  # a time counter that wraps at this value (unsigned 32-bit ticks)
    acc_unit: str | None = None  # None: not known from the format (the caller's, or m/s^2)
    gyr_unit: str | None = None
    rate_pattern: str | None = None  # a regular expression on the lines above the header: the rate in Hz

    @property
    def by_name(self) -> bool:
        return isinstance(self.channels[0], str)


_XSENS_CHANNELS = ("Acc_X", "Acc_Y", "Acc_Z", "Gyr_X", "Gyr_Y", "Gyr_Z")
PRESETS: dict[str, CsvLayout] = {
    # x-IMU3 GUI: Inertial.csv, ``Timestamp (us)``, gyroscope (deg/s) then accelerometer (g).
    "ximu3": CsvLayout(
        "ximu3",
        tuple(f"Accelerometer {a} (g)" for a in "XYZ") + tuple(f"Gyroscope {a} (deg/s)" for a in "XYZ"),
        time="Timestamp (us)",
        time_scale_s=1e-6,
        acc_unit="g",
        gyr_unit="deg/s",
    ),
    # Movella (Xsens) DOT app export: metadata lines (``OutputRate:,60Hz``), then PacketCounter, SampleTimeFine
    # (µs, unsigned 32-bit) and the measurement mode's columns; Acc in m/s², Gyr in deg/s.
    "movella-dot": CsvLayout(
        "movella-dot",
        _XSENS_CHANNELS,
        time="SampleTimeFine",
        time_scale_s=1e-6,
        time_wrap=2.0**32,
        acc_unit="m/s^2",
        gyr_unit="deg/s",
        rate_pattern=r"OutputRate:\s*,?\s*([0-9.]+)\s*Hz",
    ),
    # Xsens MT Manager text export: ``//`` comment lines, tab- (or comma-) separated, SampleTimeFine in 10 kHz
    # ticks (left empty by some exports; then ``Update Rate: 100.0Hz`` if the header has it); Acc m/s², Gyr rad/s.
    "mt-manager": CsvLayout(
        "mt-manager",
        _XSENS_CHANNELS,
        time="SampleTimeFine",
        time_scale_s=1e-4,
        time_wrap=2.0**32,
        acc_unit="m/s^2",
        gyr_unit="rad/s",
        rate_pattern=r"Update Rate:\s*([0-9.]+)\s*Hz",
    ),
}


def parse_columns(spec: str, skip_columns: int = 0) -> CsvLayout:
    """A ``--columns`` value: a preset name (``PRESETS``); or comma-separated labels of the file's columns from
    column ``skip_columns`` on (each of ``CHANNELS`` once, ``-`` for a column to ignore, at most one of
    ``TIME_LABELS``); or the six header names of acc x, y, z, gyr x, y, z, in this order."""
    if spec in PRESETS:
        return PRESETS[spec]
    items = [item.strip() for item in spec.split(",")]
    labels = set(CHANNELS) | set(TIME_LABELS) | {IGNORED}
    if all(item in labels for item in items):
        return _by_position(items, skip_columns)
    if any(item in labels for item in items) or len(items) != 6:
        raise ColumnError(
            f"--columns takes a preset ({', '.join(PRESETS)}), labels of the file's columns in its order "
            f"({', '.join(CHANNELS)}, {IGNORED} to ignore one, {' or '.join(TIME_LABELS)}), or six header names "
            f"(acc x, y, z, gyr x, y, z); got {spec!r}"
        )
    return CsvLayout("by header name", tuple(items))


def _by_position(labels: list[str], skip_columns: int) -> CsvLayout:
    missing = [c for c in CHANNELS if labels.count(c) != 1]
    times = [k for k, label in enumerate(labels) if label in TIME_LABELS]
    if missing or len(times) > 1:
        raise ColumnError(
            f"--columns by position needs each of {', '.join(CHANNELS)} exactly once and at most one time column; "
            f"got {','.join(labels)}"
        )
    time = None if not times else skip_columns + times[0]
    scale = 1.0 if not times else TIME_LABELS[labels[times[0]]]
    channels = tuple(skip_columns + labels.index(c) for c in CHANNELS)
    return CsvLayout("by position", channels, time=time, time_scale_s=scale)


@dataclass(frozen=True)
class MappedCsv:
    """A file's readings ``(T, 6)`` (acc x, y, z, gyr x, y, z in the file's units), on a uniform grid."""

    samples: np.ndarray
    rate_hz: float | None  # from the time column or the header; None when the file gives no time
    acc_unit: str | None
    gyr_unit: str | None
    gaps: int = 0  # steps the time column skipped (dropped samples), filled by resampling onto ``rate_hz``


def read_mapped_csv(path: Path, layout: CsvLayout) -> MappedCsv:
    """Read one sensor's file with ``layout``; ``ColumnError`` (naming the file) when it does not fit."""
    lines = _read_lines(path)
    head, delimiter, header = _find_header(path, lines, layout)
    wanted = [_column(path, header, c) for c in layout.channels]
    time_col = None if layout.time is None else _column(path, header, layout.time)
    samples, t = _parse_rows(path, lines[head + 1 :], delimiter, wanted, time_col)
    if not len(samples):
        raise ColumnError(f"{path}: no data rows after the header")
    if not np.isfinite(samples).all():
        raise ColumnError(f"{path}: the six IMU columns must be finite numbers, found NaN or Inf")
    mapped = MappedCsv(samples, _header_rate(lines[:head], layout), layout.acc_unit, layout.gyr_unit)
    if t is None:
        return mapped
    return _on_uniform_grid(
        path, mapped, t * layout.time_scale_s, layout.time_wrap and layout.time_wrap * layout.time_scale_s
    )


def _read_lines(path: Path) -> list[str]:
    try:
        if path.suffix == ".gz":
            with gzip.open(path, "rt", encoding="utf-8-sig", errors="replace") as fh:
                return fh.read().splitlines()
        return path.read_text(encoding="utf-8-sig", errors="replace").splitlines()
    except OSError as exc:
        raise ColumnError(f"{path}: cannot read it ({exc.strerror or exc})") from None


def _fields(line: str, delimiter: str) -> list[str]:
    return [f.strip().strip('"') for f in line.split(delimiter)]


def _find_header(path: Path, lines: list[str], layout: CsvLayout) -> tuple[int, str, list[str]]:
    """(line index, delimiter, fields) of the header: for names, the first line holding all of them (lines above
    it are the export's metadata); by position, the first line, split by the delimiter that splits it most."""
    if not lines:
        raise ColumnError(f"{path}: the file is empty")
    if not layout.by_name:
        delimiter = max(DELIMITERS, key=lambda d: len(lines[0].split(d)))
        return 0, delimiter, _fields(lines[0], delimiter)
    names = [n for n in (*layout.channels, layout.time) if isinstance(n, str)]
    for k, line in enumerate(lines):
        for delimiter in DELIMITERS:
            fields = _fields(line, delimiter)
            if all(n in fields for n in names):
                return k, delimiter, fields
    first = next((line for line in lines if any(d in line for d in DELIMITERS)), lines[0])
    raise ColumnError(
        f"{path}: expected a header row with the columns {', '.join(names)} ({layout.name}); "
        f"the file's first header-like row is {first[:200]!r}"
    )


def _column(path: Path, header: list[str], column: str | int) -> int:
    if isinstance(column, int):
        if column >= len(header):
            raise ColumnError(f"{path}: the layout reads column {column + 1}, the header has {len(header)} column(s)")
        return column
    return header.index(column)


def _parse_rows(
    path: Path, rows: Sequence[str], delimiter: str, wanted: list[int], time_col: int | None
) -> tuple[np.ndarray, np.ndarray | None]:
    """The wanted columns of every non-blank row ``(T, 6)``, and the time column (None when it is empty
    throughout, as in exports that leave SampleTimeFine blank)."""
    values, times = [], []
    last = max(wanted + ([] if time_col is None else [time_col]))
    for n, line in enumerate(rows):
        if not line.strip() or line.lstrip().startswith(("//", "#")):
            continue
        fields = _fields(line, delimiter)
        if len(fields) <= last:
            raise ColumnError(
                f"{path}: data row {n + 1} has {len(fields)} column(s), the layout reads column {last + 1}"
            )
        try:
            values.append([float(fields[c]) for c in wanted])
        except ValueError:
            raise ColumnError(
                f"{path}: data row {n + 1}: expected numbers in the IMU columns, got {line[:120]!r}"
            ) from None
        if time_col is not None:
            times.append(fields[time_col])
    samples = np.array(values, dtype=np.float64).reshape(-1, 6)
    if time_col is None or not any(times):
        return samples, None
    try:
        return samples, np.array([float(v) for v in times])
    except ValueError:
        raise ColumnError(f"{path}: the time column must hold a number on every row") from None


def _header_rate(lines: list[str], layout: CsvLayout) -> float | None:
    if layout.rate_pattern is None:
        return None
    for line in lines:
        found = re.search(layout.rate_pattern, line)
        if found:
            return float(found.group(1))
    return None


def _on_uniform_grid(path: Path, mapped: MappedCsv, t_s: np.ndarray, wrap_s: float | None) -> MappedCsv:
    """The rate from the timestamps (their median step); rows whose steps show gaps (dropped samples, as over
    UDP or Bluetooth) are resampled by timestamp onto a uniform grid at that rate."""
    steps = np.diff(t_s)
    if wrap_s:
        steps = np.where(steps < -wrap_s / 2, steps + wrap_s, steps)
    if len(steps) == 0 or (steps <= 0).any():
        where = "a single row" if len(steps) == 0 else f"a step of {steps.min():g} s at row {int(steps.argmin()) + 2}"
        raise ColumnError(f"{path}: the time column must increase from row to row, found {where}")
    step = float(np.median(steps))
    gaps = int((steps > GAP_FACTOR * step).sum())
    out = replace(mapped, rate_hz=1.0 / step, gaps=gaps)
    if not gaps:
        return out
    t = np.concatenate([[0.0], np.cumsum(steps)])
    return replace(out, samples=resample_timestamps(t, mapped.samples, 1.0 / step)[1])
