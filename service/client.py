"""Streaming client: send a recording to ``/v1/stream`` at real time (or faster) and collect results.

    python -m service.client --recording ximu3_lowerbody --data-dir ../shared/data
    python -m service.client --csv thigh.csv --csv shank.csv --rate 100 --acc-unit g --gyr-unit deg/s
    python -m service.client --recording gaitmap_foot/imu_sample_ic_stride --worn LeftFoot --worn RightFoot
    python -m service.client --csv a.csv --csv b.csv --candidates a=LeftFoot,RightFoot --candidates b=LeftFoot,RightFoot

A CSV holds one sensor: a header row, then rows of acc_x, acc_y, acc_z, gyr_x, gyr_y, gyr_z (extra
leading columns such as time are allowed with ``--skip-columns``). ``--worn`` (repeated) declares the segments the
sensors are on, when known but not which is which; the joint and per-moment answers then come from those only.
``--candidates SENSOR=SEGMENT,SEGMENT`` (repeated) does the same for one sensor (a CSV's sensor id is its file
name without the extension).
"""

from __future__ import annotations

import argparse
import asyncio
import json
import logging
import os
import time
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np
import websockets

from service.api.protocol import encode_binary
from service.core.recordings import read_csv_imu, read_recording

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class ClientSensor:
    sensor_id: str
    samples: np.ndarray  # (T, 6) in the declared units
    sample_rate_hz: float = 60.0
    acc_unit: str = "m/s^2"
    gyr_unit: str = "rad/s"
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
) -> StreamOutcome:
    """Stream all sensors concurrently; ``speed`` 1 is real time, 0 as fast as possible. ``worn_segments``: the
    start message's (the segments the sensors are known to be on)."""
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
        receiver = asyncio.create_task(_receive(ws, outcome))
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


async def _receive(ws: websockets.ClientConnection, outcome: StreamOutcome) -> None:
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
    except websockets.ConnectionClosed:
        pass


def _csv_sensor(path: Path, rate: float, acc_unit: str, gyr_unit: str, skip: int) -> ClientSensor:
    return ClientSensor(path.stem, read_csv_imu(path, skip), rate, acc_unit, gyr_unit)


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


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--url", default="ws://127.0.0.1:8000/v1/stream")
    parser.add_argument("--recording", help="a recording of the data directory, e.g. ximu3_lowerbody")
    parser.add_argument("--data-dir", default=os.environ.get("WEARMOCAP_DATA_DIR"))
    parser.add_argument("--csv", action="append", type=Path, default=[], help="one sensor per CSV file")
    parser.add_argument("--rate", type=float, default=60.0, help="CSV sample rate in Hz")
    parser.add_argument("--acc-unit", default="m/s^2", choices=["m/s^2", "g"])
    parser.add_argument("--gyr-unit", default="rad/s", choices=["rad/s", "deg/s"])
    parser.add_argument("--skip-columns", type=int, default=0)
    parser.add_argument("--speed", type=float, default=1.0, help="1 = real time, 0 = as fast as possible")
    parser.add_argument("--json", action="store_true", help="send JSON packets instead of binary")
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
    args = parser.parse_args()
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    if args.recording:
        if not args.data_dir:
            parser.error("--recording needs --data-dir or WEARMOCAP_DATA_DIR")
        rec = read_recording(Path(args.data_dir), args.recording)
        sensors = [ClientSensor(s.sensor_id, s.imu) for s in rec.sensors]
    elif args.csv:
        sensors = [_csv_sensor(p, args.rate, args.acc_unit, args.gyr_unit, args.skip_columns) for p in args.csv]
    else:
        parser.error("give --recording or at least one --csv")
    sensors = _with_candidates(sensors, args.candidates, parser)
    outcome = asyncio.run(
        stream_sensors(
            args.url, sensors, args.speed, binary=not args.json, api_key=args.api_key, worn_segments=args.worn
        )
    )
    if args.out:
        args.out.write_text("".join(json.dumps(r) + "\n" for r in outcome.results + outcome.moments))
    for event in outcome.events:
        log.info("%s", event)
    log.info("%d window results, %d moments", len(outcome.results), len(outcome.moments))
    for s in (outcome.assignment or {}).get("sensors", []):
        alignment = s.get("alignment")
        q = "" if alignment is None else " ".join(f"{v:+.3f}" for v in alignment["q_segment_imu"])
        log.info(
            "%-32s -> %-14s confidence %.3f  margin %s  (%d moving windows)  q_segment_imu [%s] spread %s",
            s["sensor_id"],
            s["segment"],
            s["confidence"],
            "-" if s["margin"] is None else f"{s['margin']:.1f}",
            s["windows"],
            q,
            "-" if s.get("alignment_spread_deg") is None else f"{s['alignment_spread_deg']:.1f}°",
        )
    if outcome.close_code != 1000:
        raise SystemExit(f"the server closed the stream with code {outcome.close_code} (see the error above)")


if __name__ == "__main__":
    main()
