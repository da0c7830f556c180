"""Pose benchmark of the served pose models on this machine, one run, written to ``--out``
(default benchmarks/results/pose.json):

(a) ``POST /v1/pose/imu`` latency for six sensors (pose_full6, offline Bi-LSTM): 2 s and 30 s of readings;
(b) N concurrent six-sensor pose streams at 60 Hz on ``/v1/stream`` (pose_full6_stream, declared calibration,
    binary packets of ``--packet`` samples, paced in real time), in each of ``--modes``: one packet per sensor or
    one frame packet with all six sensors, JSON pose messages or binary pose blocks. Per pose message the server
    latency from sending the packet that completed its frames to receiving it (p50/p99), and the sample-to-pose
    latency that adds the model's look-ahead (5 frames, 83 ms) and the packet's own wait for its last sample;
    how many streams the service admitted (it refuses the others with 1013). The clients connect one after
    another over ``--ramp`` seconds.

The load generator shares the machine with the service (two cores here): its own cost counts against the
service's, which is why it parses with orjson.

    python -m benchmarks.bench_pose --streams 25 50 100 --seconds 15
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import json
import platform
import time
from pathlib import Path

import httpx
import numpy as np
import orjson
import websockets

from benchmarks.machine import machine_state
from benchmarks.servers import REPO, start_service, stop
from service.api.protocol import ALL_SENSORS, decode_pose_block, encode_binary
from service.inference.pose_batcher import BUSY_WINDOW_S

RESULTS = REPO / "benchmarks" / "results"
MODES = {
    "sensor": "one binary packet per sensor (sensors that stream on their own), JSON pose messages",
    "frame": "one binary frame packet with all six sensors (a suit's receiver), JSON pose messages",
    "frame-binary": "one binary frame packet with all six sensors, binary pose blocks",
}
SIX = ["Pelvis", "Head", "LeftForeArm", "RightForeArm", "LeftLowerLeg", "RightLowerLeg"]


def _readings(n: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Plausible raw readings: slowly turning sensors, gravity plus noise: q (n, 6, 4), acc (n, 6, 3)."""
    from scipy.spatial.transform import Rotation

    rng = np.random.default_rng(seed)
    t = np.arange(n) / 60.0
    rv = np.stack([0.3 * np.sin(2 * np.pi * (0.5 + 0.1 * k) * t + k) for k in range(18)], axis=1).reshape(n, 6, 3)
    R = Rotation.from_rotvec(rv.reshape(-1, 3)).as_matrix().reshape(n, 6, 3, 3)
    q = Rotation.from_matrix(R.reshape(-1, 3, 3)).as_quat(scalar_first=True).reshape(n, 6, 4)
    acc = np.einsum("tnji,j->tni", R, [0.0, 0.0, 9.81]) + rng.normal(scale=0.5, size=(n, 6, 3))
    return q, acc


def _request(n: int) -> dict:
    q, acc = _readings(n)
    return {
        "sensors": [
            {
                "sensor_id": s,
                "segment": s,
                "q_world_sensor": q[:, k].tolist(),
                "acc": acc[:, k].tolist(),
                "q_segment_sensor": [1.0, 0.0, 0.0, 0.0],
            }
            for k, s in enumerate(SIX)
        ]
    }


def bench_rest(base: str, repeats: int, translation: str = "none") -> dict:
    out = {}
    with httpx.Client(timeout=120) as c:
        for seconds in (2, 30):
            body = json.dumps(_request(60 * seconds) | {"translation": translation}).encode()
            for _ in range(3):
                c.post(
                    base + "/v1/pose/imu", content=body, headers={"content-type": "application/json"}
                ).raise_for_status()
            lat = []
            for _ in range(repeats):
                t = time.perf_counter()
                c.post(
                    base + "/v1/pose/imu", content=body, headers={"content-type": "application/json"}
                ).raise_for_status()
                lat.append((time.perf_counter() - t) * 1000)
            out[f"rest_{seconds}s_six_sensors_ms_p50"] = float(np.percentile(lat, 50))
            out[f"rest_{seconds}s_six_sensors_ms_p99"] = float(np.percentile(lat, 99))
    return out


async def _stream(
    url: str,
    seconds: float,
    packet: int,
    mode: str,
    lat: list[float],
    counts: list[int],
    start_at: float,
    translation: str = "none",
) -> None:
    frames, binary = mode.startswith("frame"), mode.endswith("binary")
    n = int(seconds * 60)
    q, acc = _readings(n + packet, seed=int(start_at * 1000) % 997)
    rows = np.concatenate([acc, np.zeros_like(acc), q], axis=2)  # (n, 6, 10)
    sent_at: dict[int, float] = {}
    await asyncio.sleep(max(0.0, start_at - time.perf_counter()))
    async with websockets.connect(url, max_size=None, ping_interval=None) as ws:
        sensors = [{"sensor_id": s, "segment": s, "q_segment_sensor": [1.0, 0.0, 0.0, 0.0]} for s in SIX]
        pose = {"calibration": "declared", "output": "binary" if binary else "json", "translation": translation}
        await ws.send(json.dumps({"type": "start", "sensors": sensors, "pose": pose}))
        await ws.recv()  # started

        async def receive() -> None:
            # a close (a refusal at capacity) ends this task quietly; the sender's next send raises it as the outcome
            with contextlib.suppress(websockets.ConnectionClosed):
                await _receive()

        async def _receive() -> None:
            async for text in ws:
                m = decode_pose_block(text) if isinstance(text, bytes) else orjson.loads(text)
                if m["type"] == "pose":
                    # the packet that completed this message's last frame (its answer needed 5 more frames)
                    last_input = m["first_frame"] + m["frames"] - 1 + 5
                    key = last_input // packet
                    if key in sent_at:
                        lat.append((time.perf_counter() - sent_at[key]) * 1000)
                    counts[0] += m["frames"]

        receiver = asyncio.create_task(receive())
        t0 = time.perf_counter()
        for p, first in enumerate(range(0, n, packet)):
            await asyncio.sleep(max(0.0, t0 + (first + packet) / 60.0 - time.perf_counter()))
            if frames:  # one message with all six sensors' samples (a suit's receiver)
                await ws.send(encode_binary(ALL_SENSORS, first, rows[first : first + packet]))
            else:  # one message per sensor and packet (sensors that stream on their own)
                for k in range(6):
                    await ws.send(encode_binary(k, first, rows[first : first + packet, k]))
            sent_at[p] = time.perf_counter()
        await ws.send(json.dumps({"type": "stop"}))
        await receiver


def _pose_batch_totals(base: str) -> tuple[float, float, float]:
    """(batches, sessions, seconds) summed over the pose worker's batches so far, from ``/metrics``."""
    text = httpx.get(base + "/metrics").text
    total = {}
    for name in (
        "wearmocap_pose_batch_sessions_count",
        "wearmocap_pose_batch_sessions_sum",
        "wearmocap_pose_batch_seconds_sum",
    ):
        total[name] = sum(float(line.rsplit(" ", 1)[1]) for line in text.splitlines() if line.startswith(name + "{"))
    return (
        total["wearmocap_pose_batch_sessions_count"],
        total["wearmocap_pose_batch_sessions_sum"],
        total["wearmocap_pose_batch_seconds_sum"],
    )


async def bench_streams(
    base: str, n: int, seconds: float, packet: int, mode: str, ramp_s: float, translation: str = "none"
) -> dict:
    url = base.replace("http", "ws") + "/v1/stream"
    before = _pose_batch_totals(base)
    lat: list[float] = []
    counts = [0]
    start_at = time.perf_counter() + 1.0
    # clients connect one after another over ramp_s seconds, as independent users would, at random phases
    tasks = [_stream(url, seconds, packet, mode, lat, counts, start_at + k * ramp_s / n, translation) for k in range(n)]
    loop_shares: list[float] = []

    async def watch() -> None:  # the service's event loop, once a second
        async with httpx.AsyncClient() as c:
            while True:
                await asyncio.sleep(1.0)
                text = (await c.get(base + "/metrics")).text
                line = next((x for x in text.splitlines() if x.startswith("wearmocap_event_loop_busy_share ")), None)
                if line is not None and line.split()[1] != "NaN":
                    loop_shares.append(float(line.split()[1]))

    watcher = asyncio.create_task(watch())
    outcomes = await asyncio.gather(*tasks, return_exceptions=True)
    watcher.cancel()
    await asyncio.gather(watcher, return_exceptions=True)
    await asyncio.sleep(BUSY_WINDOW_S + 1.0)  # the next round is admitted on its own load, not on this one's
    batches, sessions, busy = (b - a for a, b in zip(before, _pose_batch_totals(base), strict=True))
    errors = [o for o in outcomes if isinstance(o, BaseException)]
    refused = [e for e in errors if getattr(getattr(e, "rcvd", None), "code", None) == 1013]
    failed = [repr(e)[:200] for e in errors if e not in refused]
    admitted = n - len(refused)
    expected = admitted * (int(seconds * 60) - 5)
    return {
        "streams": n,
        "translation": translation,
        "streams_admitted": admitted,
        "streams_refused_1013": len(refused),
        "first_refusal": repr(refused[0])[:200] if refused else None,
        "streams_failed": len(failed),
        "first_failure": failed[0] if failed else None,
        "packet_samples": packet,
        "ramp_s": ramp_s,
        "mode": MODES[mode],
        "pose_frames_received": counts[0],
        "pose_frames_expected_of_admitted": expected,
        "server_latency_ms_p50": float(np.percentile(lat, 50)) if lat else None,
        "server_latency_ms_p99": float(np.percentile(lat, 99)) if lat else None,
        # sample to pose: the first sample of a packet waits (packet - 1) frames for the packet to fill, every
        # answer waits 5 frames of look-ahead, then the server's time
        "sample_to_pose_ms_p99": float(np.percentile(lat, 99) + (packet - 1 + 5) * 1000 / 60.0) if lat else None,
        # the pose worker over the whole round (ramp and the streams' seconds): how busy, and how large its batches
        "pose_worker_busy_share": busy / (ramp_s + seconds),
        "pose_batch_sessions_mean": sessions / batches if batches else None,
        "pose_batch_ms_mean": 1000 * busy / batches if batches else None,
        # the event loop's thread on the CPU, of the last 2 s, sampled once a second: median and highest
        "event_loop_busy_share_median": float(np.median(loop_shares)) if loop_shares else None,
        "event_loop_busy_share_max": max(loop_shares) if loop_shares else None,
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--streams", type=int, nargs="+", default=[10, 50, 100])
    ap.add_argument("--seconds", type=float, default=15.0)
    ap.add_argument("--packet", type=int, default=4, help="samples per sensor per packet")
    ap.add_argument("--repeats", type=int, default=30)
    ap.add_argument("--ramp", type=float, default=5.0, help="seconds over which the clients connect")
    ap.add_argument(
        "--modes",
        nargs="+",
        choices=sorted(MODES),
        default=sorted(MODES),
        help="; ".join(f"{k}: {v}" for k, v in MODES.items()),
    )
    ap.add_argument(
        "--translation",
        choices=["none", "feet", "learned", "all"],
        default="none",
        help="the pose answers' translation (REST, streams); all: none, feet and learned side by side on one server",
    )
    ap.add_argument("--out", type=Path, default=RESULTS / "pose.json", help="where the results go")
    args = ap.parse_args()
    start = machine_state(REPO / "onnx_models", "start")  # how fast the machine ran (benchmarks/machine.py)
    proc, base = start_service(REPO / "onnx_models")
    try:
        served = {k: v["version"] for k, v in httpx.get(base + "/v1/models").json().items()}
        translations = ["none", "feet", "learned"] if args.translation == "all" else [args.translation]
        out = {
            "command": "python -m benchmarks.bench_pose "
            f"--streams {' '.join(map(str, args.streams))} --seconds {args.seconds} --packet {args.packet} "
            f"--ramp {args.ramp} --modes {' '.join(args.modes)} --repeats {args.repeats} "
            f"--translation {args.translation}",
            "machine": platform.processor() or platform.machine(),
            "served": served,
            "machine_state": [start],
        }
        for translation in translations:  # with all, each one's REST figures under keys ending in its name
            suffix = f"_{translation}" if args.translation == "all" else ""
            out |= {f"{k}{suffix}": v for k, v in bench_rest(base, args.repeats, translation).items()}
        out["streams"] = [
            asyncio.run(bench_streams(base, n, args.seconds, args.packet, mode, args.ramp, translation))
            for translation in translations
            for mode in args.modes
            for n in args.streams
        ]
    finally:
        stop(proc)
    out["machine_state"].append(machine_state(REPO / "onnx_models", "end"))
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(out, indent=1) + "\n")
    print(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
