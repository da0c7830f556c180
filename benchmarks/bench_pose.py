"""Pose benchmark of the served pose models on this machine, one run, written to benchmarks/results/pose.json:

(a) ``POST /v1/pose/imu`` latency for six sensors (pose_full6, offline Bi-LSTM): 2 s and 30 s of readings;
(b) N concurrent six-sensor pose streams at 60 Hz on ``/v1/stream`` (pose_full6_stream, declared calibration,
    binary packets of ``--packet`` samples per sensor, paced in real time): per pose message the server latency
    from sending the packet that completed its frames to receiving it (p50/p99), and the sample-to-pose latency
    that adds the model's look-ahead (5 frames, 83 ms) and the packet's own wait for its last sample.

    python -m benchmarks.bench_pose --streams 10 50 100 --seconds 15
"""

from __future__ import annotations

import argparse
import asyncio
import json
import platform
import time

import httpx
import numpy as np
import websockets

from benchmarks.servers import REPO, start_service, stop
from service.api.protocol import encode_binary

RESULTS = REPO / "benchmarks" / "results"
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


def bench_rest(base: str, repeats: int) -> dict:
    out = {}
    with httpx.Client(timeout=120) as c:
        for seconds in (2, 30):
            body = json.dumps(_request(60 * seconds)).encode()
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


async def _stream(url: str, seconds: float, packet: int, lat: list[float], counts: list[int], start_at: float) -> None:
    n = int(seconds * 60)
    q, acc = _readings(n + packet, seed=int(start_at * 1000) % 997)
    rows = np.concatenate([acc, np.zeros_like(acc), q], axis=2)  # (n, 6, 10)
    sent_at: dict[int, float] = {}
    async with websockets.connect(url, max_size=None, ping_interval=None) as ws:
        sensors = [{"sensor_id": s, "segment": s, "q_segment_sensor": [1.0, 0.0, 0.0, 0.0]} for s in SIX]
        await ws.send(json.dumps({"type": "start", "sensors": sensors, "pose": {"calibration": "declared"}}))
        await ws.recv()  # started

        async def receive() -> None:
            async for text in ws:
                m = json.loads(text)
                if m["type"] == "pose":
                    # the packet that completed this message's last frame (its answer needed 5 more frames)
                    last_input = m["first_frame"] + m["frames"] - 1 + 5
                    key = last_input // packet
                    if key in sent_at:
                        lat.append((time.perf_counter() - sent_at[key]) * 1000)
                    counts[0] += m["frames"]

        receiver = asyncio.create_task(receive())
        await asyncio.sleep(max(0.0, start_at - time.perf_counter()))
        t0 = time.perf_counter()
        for p, first in enumerate(range(0, n, packet)):
            await asyncio.sleep(max(0.0, t0 + (first + packet) / 60.0 - time.perf_counter()))
            for k in range(6):
                await ws.send(encode_binary(k, first, rows[first : first + packet, k]))
            sent_at[p] = time.perf_counter()
        await ws.send(json.dumps({"type": "stop"}))
        await receiver


async def bench_streams(base: str, n: int, seconds: float, packet: int) -> dict:
    url = base.replace("http", "ws") + "/v1/stream"
    lat: list[float] = []
    counts = [0]
    start_at = time.perf_counter() + 2.0
    # staggered starts within one packet interval, as independent clients would be
    tasks = [_stream(url, seconds, packet, lat, counts, start_at + k * packet / 60.0 / n) for k in range(n)]
    outcomes = await asyncio.gather(*tasks, return_exceptions=True)
    failed = [repr(o)[:120] for o in outcomes if isinstance(o, BaseException)]
    expected = n * (int(seconds * 60) - 5)
    return {
        "streams": n,
        "streams_failed": len(failed),
        "first_failure": failed[0] if failed else None,
        "packet_samples": packet,
        "pose_frames_received": counts[0],
        "pose_frames_expected": expected,
        "server_latency_ms_p50": float(np.percentile(lat, 50)) if lat else None,
        "server_latency_ms_p99": float(np.percentile(lat, 99)) if lat else None,
        # sample to pose: the first sample of a packet waits (packet - 1) frames for the packet to fill, every
        # answer waits 5 frames of look-ahead, then the server's time
        "sample_to_pose_ms_p99": float(np.percentile(lat, 99) + (packet - 1 + 5) * 1000 / 60.0) if lat else None,
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--streams", type=int, nargs="+", default=[10, 50, 100])
    ap.add_argument("--seconds", type=float, default=15.0)
    ap.add_argument("--packet", type=int, default=4, help="samples per sensor per packet")
    ap.add_argument("--repeats", type=int, default=30)
    args = ap.parse_args()
    proc, base = start_service(REPO / "onnx_models", threads=1)
    try:
        served = {k: v["version"] for k, v in httpx.get(base + "/v1/models").json().items()}
        out = {
            "machine": platform.processor() or platform.machine(),
            "served": served,
            **bench_rest(base, args.repeats),
        }
        out["streams"] = [asyncio.run(bench_streams(base, n, args.seconds, args.packet)) for n in args.streams]
    finally:
        stop(proc)
    RESULTS.mkdir(parents=True, exist_ok=True)
    (RESULTS / "pose.json").write_text(json.dumps(out, indent=1) + "\n")
    print(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
