"""Streaming client: send a recording to ``/v1/stream`` at real time (or faster) and show the answers as they come.

    python -m service.client --preset ximu3 --csv examples/ximu3_lowerbody/*.csv
    python -m service.client --recording ximu3_lowerbody --data-dir ../shared/data
    python -m service.client --csv thigh.csv --csv shank.csv --rate 100 --acc-unit g --gyr-unit deg/s
    python -m service.client --csv a.csv b.csv --columns time_s,gyr_x,gyr_y,gyr_z,acc_x,acc_y,acc_z
    python -m service.client --recording gaitmap_foot/imu_sample_ic_stride --worn LeftFoot --worn RightFoot
    python -m service.client --csv a.csv --csv b.csv --candidates a=LeftFoot,RightFoot --candidates b=LeftFoot,RightFoot

A CSV holds one sensor. Without ``--columns`` or ``--preset``: a header row, then rows of acc_x, acc_y, acc_z,
gyr_x, gyr_y, gyr_z (extra leading columns such as time are allowed with ``--skip-columns``). ``--columns`` maps
another order: labels of the file's columns in its order (``gyr_x,gyr_y,gyr_z,acc_x,acc_y,acc_z``; ``-`` for a
column to ignore; ``time_s``, ``time_ms`` or ``time_us`` for a time column, which gives the rate), or the six
header names of acc x, y, z, gyr x, y, z. ``--preset`` (or ``--columns PRESET``) reads a device's own export with
its units and rate: ``ximu3`` (x-IMU3 ``Inertial.csv``), ``movella-dot`` (Movella DOT app CSV), ``mt-manager``
(Xsens MT Manager text export). ``--rate``, ``--acc-unit`` and ``--gyr-unit`` override what a preset says.

``--worn`` (repeated) declares the segments the sensors are on, when known but not which is which; the joint and
per-moment answers then come from those only. ``--candidates SENSOR=SEGMENT,SEGMENT`` (repeated) does the same for
one sensor (a CSV's sensor id is its file name without the extension, or its folder's name when several files
share a name, as x-IMU3's ``Inertial.csv`` do).

On a terminal the answers are shown live in a table (``--display live``); otherwise the notices are logged as they
come (``plain``), or every message is printed as one JSON line (``--display json``). The summary follows.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import logging
import os
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import NoReturn

import numpy as np
import websockets
from rich.console import Console
from rich.live import Live

from service.api.protocol import encode_binary
from service.client_display import LiveView, PlainNotices, log_summary
from service.core.csv_columns import PRESETS, ColumnError, CsvLayout, parse_columns, read_mapped_csv
from service.core.recordings import read_csv_imu, read_recording
from service.core.units import ACC_UNITS, GYR_UNITS, to_contract_units, unit_warnings_over

log = logging.getLogger(__name__)

DEFAULT_RATE_HZ, DEFAULT_ACC_UNIT, DEFAULT_GYR_UNIT = 60.0, "m/s^2", "rad/s"


@dataclass(frozen=True)
class ClientSensor:
    sensor_id: str
    samples: np.ndarray  # (T, 6) in the declared units
    sample_rate_hz: float = DEFAULT_RATE_HZ
    acc_unit: str = DEFAULT_ACC_UNIT
    gyr_unit: str = DEFAULT_GYR_UNIT
    candidate_segments: list[str] | None = None  # the segments this sensor may be on (default: any)


@dataclass
class StreamOutcome:
    results: list[dict] = field(default_factory=list)
    moments: list[dict] = field(default_factory=list)  # one-to-one answers per window end time
    assignment: dict | None = None
    events: list[dict] = field(default_factory=list)  # started, gap, late, error
    close_code: int | None = None


def _schedule(sensors: list[ClientSensor], packet_samples: int) -> list[tuple[float, int, int]]:
    """(send time s, sensor index, first sample) of every packet, in time order."""
    plan = [
        ((start + packet_samples) / s.sample_rate_hz, k, start)
        for k, s in enumerate(sensors)
        for start in range(0, len(s.samples), packet_samples)
    ]
    return sorted(plan)


async def stream_sensors(
    url: str,
    sensors: list[ClientSensor],
    speed: float = 1.0,
    packet_samples: int = 16,
    binary: bool = True,
    api_key: str | None = None,
    worn_segments: list[str] | None = None,
    on_message: Callable[[dict], None] | None = None,
) -> StreamOutcome:
    """Stream all sensors concurrently; ``speed`` 1 is real time, 0 as fast as possible. ``worn_segments``: the
    start message's (the segments the sensors are known to be on). ``on_message`` sees every message the server
    sends, as it arrives."""
    outcome = StreamOutcome()
    headers = {"X-API-Key": api_key} if api_key else None
    async with websockets.connect(url, additional_headers=headers, max_size=2**24) as ws:
        start = {
            "type": "start",
            "sensors": [
                {
                    "sensor_id": s.sensor_id,
                    "sample_rate_hz": s.sample_rate_hz,
                    "acc_unit": s.acc_unit,
                    "gyr_unit": s.gyr_unit,
                }
                | ({} if s.candidate_segments is None else {"candidate_segments": s.candidate_segments})
                for s in sensors
            ],
        }
        if worn_segments is not None:
            start["worn_segments"] = worn_segments
        await ws.send(json.dumps(start))
        receiver = asyncio.create_task(_receive(ws, outcome, on_message))
        t0 = time.monotonic()
        for due_s, k, first in _schedule(sensors, packet_samples):
            if speed > 0:
                delay = due_s / speed - (time.monotonic() - t0)
                if delay > 0:
                    await asyncio.sleep(delay)
            chunk = sensors[k].samples[first : first + packet_samples]
            if binary:
                await ws.send(encode_binary(k, first, chunk))
            else:
                await ws.send(
                    json.dumps(
                        {
                            "type": "samples",
                            "sensor_id": sensors[k].sensor_id,
                            "seq": first,
                            "samples": np.asarray(chunk).tolist(),
                        }
                    )
                )
        await ws.send(json.dumps({"type": "stop"}))
        await receiver
        outcome.close_code = ws.close_code
    return outcome


async def _receive(
    ws: websockets.ClientConnection, outcome: StreamOutcome, on_message: Callable[[dict], None] | None
) -> None:
    try:
        async for raw in ws:
            message = json.loads(raw)
            if message["type"] == "result":
                outcome.results.append(message)
            elif message["type"] == "moment":
                outcome.moments.append(message)
            elif message["type"] == "assignment":
                outcome.assignment = message
            else:
                outcome.events.append(message)
            if on_message is not None:
                on_message(message)
    except websockets.ConnectionClosed:
        pass


def csv_sensor_ids(paths: list[Path]) -> list[str]:
    """A sensor id per file: its name without the extension, or, where files share a name (x-IMU3 writes an
    ``Inertial.csv`` per device folder), its folder's name."""
    stems = [p.name.removesuffix(".gz").rsplit(".", 1)[0] for p in paths]
    if len(set(stems)) == len(stems):
        return stems
    folders = [p.resolve().parent.name for p in paths]
    return folders if len(set(folders)) == len(folders) else [str(p) for p in paths]


def read_csv_sensor(
    path: Path,
    sensor_id: str,
    layout: CsvLayout | None = None,
    skip_columns: int = 0,
    rate_hz: float | None = None,
    acc_unit: str | None = None,
    gyr_unit: str | None = None,
) -> ClientSensor:
    """One CSV file as a sensor: read as acc then gyr (``read_csv_imu``) without a layout, or by ``layout``. The
    rate and units given here win; then the file's (a preset's units, the rate of its time column or header);
    then 60 Hz, m/s² and rad/s. A preset's file that gives no rate needs ``rate_hz`` (``ColumnError``)."""
    if not path.is_file():
        raise ColumnError(f"{path}: no such file" if not path.exists() else f"{path}: not a file")
    gaps, file_rate, file_acc, file_gyr = 0, None, None, None
    if layout is None:
        samples = read_csv_imu(path, skip_columns)
    else:
        mapped = read_mapped_csv(path, layout)
        samples, gaps, file_rate = mapped.samples, mapped.gaps, mapped.rate_hz
        file_acc, file_gyr = mapped.acc_unit, mapped.gyr_unit
        if file_rate is None and rate_hz is None and layout.name in PRESETS:
            raise ColumnError(f"{path}: the file gives no sample rate ({layout.name}): give --rate")
    if rate_hz is not None and file_rate is not None and abs(rate_hz / file_rate - 1) > 0.02:
        log.warning("%s: --rate %g Hz, but the file says %.4g Hz; sending %g Hz", path, rate_hz, file_rate, rate_hz)
    sensor = ClientSensor(
        sensor_id,
        samples,
        rate_hz or file_rate or DEFAULT_RATE_HZ,
        acc_unit or file_acc or DEFAULT_ACC_UNIT,
        gyr_unit or file_gyr or DEFAULT_GYR_UNIT,
    )
    log.info(
        "%s: sensor %s, %d samples at %.4g Hz%s, acc %s, gyr %s",
        path,
        sensor_id,
        len(samples),
        sensor.sample_rate_hz,
        f" (resampled by timestamp over {gaps} gap(s))" if gaps else "",
        sensor.acc_unit,
        sensor.gyr_unit,
    )
    return sensor


def check_units(sensor: ClientSensor) -> list[str]:
    """``unit_warnings_over`` the sensor's readings: what a mistaken unit or column mapping looks like (gravity far
    from 9.81 m/s², a gyroscope faster than a human segment turns)."""
    readings = to_contract_units(sensor.samples, sensor.acc_unit, sensor.gyr_unit)
    return unit_warnings_over(readings, sensor.sample_rate_hz, sensor.acc_unit, sensor.gyr_unit)


def _with_candidates(
    sensors: list[ClientSensor], declared: list[str], parser: argparse.ArgumentParser
) -> list[ClientSensor]:
    """Attach each ``SENSOR=SEGMENT,SEGMENT`` of ``--candidates`` to its sensor (the server checks the names)."""
    ids = [s.sensor_id for s in sensors]
    candidates: dict[str, list[str]] = {}
    for item in declared:
        sensor_id, _, names = item.partition("=")
        if sensor_id not in ids or not names:
            parser.error(f"--candidates takes SENSOR=SEGMENT,SEGMENT with SENSOR one of {ids}; got {item!r}")
        candidates[sensor_id] = names.split(",")
    return [replace(s, candidate_segments=candidates.get(s.sensor_id)) for s in sensors]


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="python -m service.client", description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--url", default="ws://127.0.0.1:8000/v1/stream")
    parser.add_argument("--recording", help="a recording of the data directory, e.g. ximu3_lowerbody")
    parser.add_argument("--data-dir", default=os.environ.get("WEARMOCAP_DATA_DIR"))
    parser.add_argument(
        "--csv", action="extend", nargs="+", type=Path, default=[], metavar="FILE", help="one sensor per CSV file"
    )
    parser.add_argument("--columns", help="the files' column layout: labels in file order, header names, or a preset")
    parser.add_argument("--preset", choices=sorted(PRESETS), help="a device's export format (units and rate too)")
    parser.add_argument(
        "--rate", type=float, help=f"CSV sample rate in Hz (default: the file's, else {DEFAULT_RATE_HZ:g})"
    )
    parser.add_argument("--acc-unit", choices=list(ACC_UNITS), help="default: the preset's, else m/s^2")
    parser.add_argument("--gyr-unit", choices=list(GYR_UNITS), help="default: the preset's, else rad/s")
    parser.add_argument("--skip-columns", type=int, default=0, help="leading columns before the readings (or labels)")
    parser.add_argument("--speed", type=float, default=1.0, help="1 = real time, 0 = as fast as possible")
    parser.add_argument("--json", action="store_true", help="send JSON packets instead of binary")
    parser.add_argument(
        "--display",
        choices=["auto", "live", "plain", "json"],
        default="auto",
        help="live table (auto: when stdout is a terminal), plain log lines, or one JSON line per message",
    )
    parser.add_argument("--out", type=Path, help="write every result and moment message to this JSON-lines file")
    parser.add_argument("--api-key", default=os.environ.get("WEARMOCAP_API_KEY"))
    parser.add_argument(
        "--worn", action="append", metavar="SEGMENT", help="a segment the sensors are on (repeat; default: any)"
    )
    parser.add_argument(
        "--candidates",
        action="append",
        default=[],
        metavar="SENSOR=SEGMENT,SEGMENT",
        help="the segments one sensor may be on (repeat per sensor; default: any)",
    )
    return parser


def _csv_layout(args: argparse.Namespace, parser: argparse.ArgumentParser) -> CsvLayout | None:
    if args.preset and args.columns:
        parser.error("give --preset or --columns, not both")
    if args.preset:
        return PRESETS[args.preset]
    if args.columns is None:
        return None
    try:
        return parse_columns(args.columns, args.skip_columns)
    except ColumnError as exc:
        parser.error(str(exc))


def _sensors(args: argparse.Namespace, parser: argparse.ArgumentParser) -> list[ClientSensor]:
    if args.recording:
        if args.csv or args.columns or args.preset:
            parser.error("--csv, --columns and --preset are for CSV files, not --recording")
        if not args.data_dir:
            parser.error("--recording needs --data-dir or WEARMOCAP_DATA_DIR")
        try:
            rec = read_recording(Path(args.data_dir), args.recording)
        except KeyError as exc:
            _fail(parser, exc.args[0])
        return [ClientSensor(s.sensor_id, s.imu) for s in rec.sensors]
    if not args.csv:
        parser.error("give --recording or at least one --csv")
    layout = _csv_layout(args, parser)
    units = {"rate_hz": args.rate, "acc_unit": args.acc_unit, "gyr_unit": args.gyr_unit}
    sensors = []
    for path, sensor_id in zip(args.csv, csv_sensor_ids(args.csv), strict=True):
        try:
            sensors.append(read_csv_sensor(path, sensor_id, layout, args.skip_columns, **units))
        except ValueError as exc:  # ColumnError, read_csv_imu's errors
            _fail(parser, str(exc))
    for s in sensors:
        for warning in check_units(s):
            log.warning("%s: %s", s.sensor_id, warning)
    return sensors


def _fail(parser: argparse.ArgumentParser, message: str) -> NoReturn:
    """One line on stderr, exit status 2: what went wrong with the input, no traceback."""
    parser.exit(2, f"{parser.prog}: error: {message}\n")


def _display(choice: str) -> str:
    if choice != "auto":
        return choice
    return "live" if sys.stdout.isatty() else "plain"


def _stream(
    args: argparse.Namespace, sensors: list[ClientSensor], display: str, console: Console | None = None
) -> StreamOutcome:
    """Run the stream with the chosen display of the messages as they arrive (``console``: the live table's,
    default the terminal)."""

    def run(on_message: Callable[[dict], None]) -> StreamOutcome:
        coroutine = stream_sensors(
            args.url,
            sensors,
            args.speed,
            binary=not args.json,
            api_key=args.api_key,
            worn_segments=args.worn,
            on_message=on_message,
        )
        return asyncio.run(coroutine)

    if display == "json":
        return run(lambda m: print(json.dumps(m), flush=True))
    if display == "plain":
        return run(PlainNotices())
    view = LiveView([s.sensor_id for s in sensors])
    with Live(view, console=console, refresh_per_second=4):
        return run(view.update)


def main() -> None:
    parser = _parser()
    args = parser.parse_args()
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    sensors = _with_candidates(_sensors(args, parser), args.candidates, parser)
    display = _display(args.display)
    try:
        outcome = _stream(args, sensors, display)
    except OSError as exc:
        raise SystemExit(f"could not reach {args.url}: {exc.strerror or exc} (is the service running?)") from None
    except websockets.InvalidStatus as exc:
        raise SystemExit(f"{args.url} refused the stream: HTTP {exc.response.status_code}") from None
    if args.out:
        args.out.write_text("".join(json.dumps(r) + "\n" for r in outcome.results + outcome.moments))
    log_summary(outcome, notices_logged=display == "plain")
    if outcome.close_code != 1000:
        raise SystemExit(f"the server closed the stream with code {outcome.close_code} (see the error above)")


if __name__ == "__main__":
    main()
