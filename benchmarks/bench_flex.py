"""Flex benchmark of the served flex models on this machine, one run, written to benchmarks/results/flex.json:

(a) ``POST /v1/pose/flex`` latency for a 10 s and a 60 s block of each shipped flex model (every sample after the
    calibration window answered);
(b) N concurrent ``/v1/stream/flex`` streams of the simulated-suit model at its 20 Hz, binary packets of
    ``--packet`` samples paced in real time: per angles message the server latency from sending the packet to
    receiving its answers (p50/p99), and whether the server kept up (answers per second against the readings').

    python -m benchmarks.bench_flex --streams 1 10 50 --seconds 15
"""

from __future__ import annotations

import argparse
import asyncio
import json
import platform
import time
from pathlib import Path

import httpx
import numpy as np
import websockets

from benchmarks.machine import machine_state
from benchmarks.servers import REPO, served_dir, start_service, stop
from service.api.protocol import encode_binary
from service.core.manifest import read_manifest

RESULTS = REPO / "benchmarks" / "results"


MODELS = {name: served_dir(name).name for name in ("flex_bilstm_cm", "flex_capacitive_knee")}


def _readings(name: str, n: int, seed: int = 0) -> np.ndarray:
    """Plausible readings inside the model's range: slow sines about the middle of its training inputs."""
    m = read_manifest(REPO / "onnx_models" / name / MODELS[name] / "manifest.json")
    rng = np.random.default_rng(seed)
    t = np.arange(n) / m.sample_rate_hz
    c = len(m.channels)
    base, amp = (2000.0, 800.0) if m.value_range else (10_000.0, 100.0)
    x = base + amp * np.sin(2 * np.pi * 0.8 * t[:, None] + np.arange(c)) + rng.normal(0, 3, (n, c))
    return np.clip(x, *(m.value_range or (-np.inf, np.inf))).astype(np.float32)


def rest(base: str, repeats: int = 5) -> dict:
    out = {}
    with httpx.Client(timeout=120) as client:
        for name in MODELS:
            rate = read_manifest(REPO / "onnx_models" / name / MODELS[name] / "manifest.json").sample_rate_hz
            for seconds in (10, 60):
                x = _readings(name, int(seconds * rate))
                body = {"model": name, "samples": x.tolist()}
                client.post(f"{base}/v1/pose/flex", json=body).raise_for_status()
                times = []
                for _ in range(repeats):
                    t0 = time.perf_counter()
                    r = client.post(f"{base}/v1/pose/flex", json=body)
                    times.append((time.perf_counter() - t0) * 1e3)
                    r.raise_for_status()
                out[f"{name}_{seconds}s"] = {"frames": r.json()["frames"], "median_ms": float(np.median(times))}
    return out


async def _one_stream(
    url: str, x: np.ndarray, packet: int, rate: float, lat: list[float], frames: list[int], refusals: list[str]
) -> bool:
    """One session streamed at real time; False when the service refused it at capacity (close code 1013, its
    reason in ``refusals``)."""
    async with websockets.connect(url, max_size=None) as ws:
        sent: dict[int, float] = {}

        async def receive() -> None:
            async for text in ws:
                m = json.loads(text)
                if m["type"] == "angles":
                    end = m["first_sample"] + m["frames"] - 1 + 1  # latency 1: the newest reading answered is +1
                    seq = max(k for k in sent if k <= end)
                    lat.append((time.perf_counter() - sent[seq]) * 1e3)
                    frames.append(m["frames"])

        task: asyncio.Task | None = None
        try:
            await ws.send(json.dumps({"type": "start", "model": "flex_bilstm_cm", "channels": _channels()}))
            json.loads(await ws.recv())
            task = asyncio.create_task(receive())
            t0 = time.perf_counter()
            for k in range(0, len(x) - packet + 1, packet):
                await asyncio.sleep(max(0.0, t0 + (k + packet) / rate - time.perf_counter()))
                sent[k + packet - 1] = time.perf_counter()
                await ws.send(encode_binary(0, k, x[k : k + packet]))
            await ws.send(json.dumps({"type": "stop"}))
            await task
        except websockets.exceptions.ConnectionClosedError as e:
            if task is not None:  # its receive loop ended on the same close: collect it
                task.cancel()
                await asyncio.gather(task, return_exceptions=True)
            if e.rcvd is None or e.rcvd.code != 1013:
                raise
            refusals.append(
                e.rcvd.reason.split(":")[1].split(";")[0].strip() if ":" in e.rcvd.reason else e.rcvd.reason
            )
            return False
        return True


def _channels() -> list[str]:
    return read_manifest(REPO / "onnx_models" / "flex_bilstm_cm" / MODELS["flex_bilstm_cm"] / "manifest.json").channels


async def streams(base: str, n: int, seconds: float, packet: int) -> dict:
    rate = 20.0
    url = base.replace("http", "ws") + "/v1/stream/flex"
    lat: list[float] = []
    frames: list[int] = []
    refusals: list[str] = []
    x = [_readings("flex_bilstm_cm", int(seconds * rate), seed=k) for k in range(n)]
    t0 = time.perf_counter()
    admitted = await asyncio.gather(*(_one_stream(url, x[k], packet, rate, lat, frames, refusals) for k in range(n)))
    wall = time.perf_counter() - t0
    expected = sum(admitted) * (int(seconds * rate) - 99)
    return {
        "streams": n,
        "refused_at_capacity": n - sum(admitted),
        "refusal_reasons": sorted(set(refusals)),
        "answers": int(sum(frames)),
        "answers_expected": expected,
        "answers_per_s": sum(frames) / wall,
        "server_latency_p50_ms": float(np.percentile(lat, 50)) if lat else None,
        "server_latency_p99_ms": float(np.percentile(lat, 99)) if lat else None,
        "wall_s": wall,
    }


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--streams", type=int, nargs="+", default=[1, 10, 50])
    ap.add_argument("--seconds", type=float, default=15.0)
    ap.add_argument("--packet", type=int, default=2, help="samples per packet (2 at 20 Hz: every 100 ms)")
    ap.add_argument("--out", type=Path, default=RESULTS / "flex.json", help="where the results go")
    args = ap.parse_args()
    start = machine_state(REPO / "onnx_models", "start")  # how fast the machine ran (benchmarks/machine.py)
    server, base = start_service(REPO / "onnx_models")
    try:
        result = {"machine": f"{platform.processor() or platform.machine()}, {__import__('os').cpu_count()} cores"}
        result["machine_state"] = [start]
        result["models"] = MODELS
        result["rest"] = rest(base)
        result["streams"] = [asyncio.run(streams(base, n, args.seconds, args.packet)) for n in args.streams]
    finally:
        stop(server)
    result["machine_state"].append(machine_state(REPO / "onnx_models", "end"))
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(result, indent=1))
    print(json.dumps(result, indent=1))


if __name__ == "__main__":
    main()
