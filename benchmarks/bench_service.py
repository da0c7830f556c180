"""Service benchmark on this machine, all measured in one run and written to benchmarks/results/service.json:

(a) single-window POST latency and batched POST throughput (assignment + alignment);
(b) N concurrent WebSocket streams at 60 Hz: samples/s sustained, result latency p50/p99, samples lost;
(c) the assignment ONNX model behind our service vs behind ``mlflow models serve``, same batches, as a ratio.

    python -m benchmarks.bench_service --streams 50 100 200 --stream-seconds 15
"""

from __future__ import annotations

import argparse
import asyncio
import json
import platform
import shutil
import tempfile
import time
from pathlib import Path

import httpx
import mlflow
import numpy as np
import websockets

from benchmarks.servers import REPO, start_mlflow_serve, start_service, stop
from service.api.protocol import encode_binary
from service.core.manifest import read_manifest

RESULTS = REPO / "benchmarks" / "results"


def _latest(task_dir: Path) -> Path:
    return sorted(p.parent for p in task_dir.glob("*/manifest.json"))[-1]


def _windows(n: int, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    x = rng.normal(size=(n, 128, 6)).astype(np.float32)
    x[..., 2] += 9.81
    return x


def _pct(values: list[float], q: float) -> float:
    return float(np.percentile(values, q)) if values else float("nan")


def bench_rest(base: str, n_single: int, batch: int, n_batches: int) -> dict:
    payload_one = {"windows": [{"samples": w.tolist()} for w in _windows(1)]}
    payload_batch = {"windows": [{"samples": w.tolist()} for w in _windows(batch)]}
    body_batch = json.dumps(payload_batch)
    with httpx.Client(timeout=60) as c:
        for _ in range(10):
            c.post(f"{base}/v1/imu/windows", json=payload_one)
        lat = []
        for _ in range(n_single):
            t = time.perf_counter()
            r = c.post(f"{base}/v1/imu/windows", json=payload_one)
            lat.append((time.perf_counter() - t) * 1000)
            r.raise_for_status()
        t = time.perf_counter()
        for _ in range(n_batches):
            c.post(
                f"{base}/v1/imu/windows", content=body_batch, headers={"content-type": "application/json"}
            ).raise_for_status()
        elapsed = time.perf_counter() - t
    return {
        "single_window_post_ms_p50": _pct(lat, 50),
        "single_window_post_ms_p99": _pct(lat, 99),
        "batched_windows_per_s": batch * n_batches / elapsed,
        "batch_size": batch,
    }


async def _one_stream(
    url: str, seconds: float, lat_ms: list[float], sent: list[int], start_at: float, failures: list[str]
) -> None:
    try:
        await _stream_body(url, seconds, lat_ms, sent, start_at)
    except (websockets.ConnectionClosed, OSError) as exc:
        failures.append(type(exc).__name__ + ": " + str(exc)[:120])


async def _stream_body(url: str, seconds: float, lat_ms: list[float], sent: list[int], start_at: float) -> None:
    x = _windows(1, seed=len(sent))[0]
    samples = np.tile(x, (int(seconds * 60 / 128) + 2, 1))[: int(seconds * 60)]
    pending: dict[float, float] = {}
    async with websockets.connect(url, max_size=2**24, ping_interval=None) as ws:
        await ws.send(json.dumps({"type": "start", "sensors": [{"sensor_id": "s"}]}))
        await ws.recv()

        async def receive() -> None:
            async for raw in ws:
                m = json.loads(raw)
                if m["type"] == "result":
                    t_sent = pending.pop(round(m["window_end_s"], 4), None)
                    if t_sent is not None:
                        lat_ms.append((time.perf_counter() - t_sent) * 1000)

        rx = asyncio.create_task(receive())
        await asyncio.sleep(max(0.0, start_at - time.perf_counter()))
        t0 = time.perf_counter()
        for first in range(0, len(samples), 16):
            due = t0 + (first + 16) / 60.0
            await asyncio.sleep(max(0.0, due - time.perf_counter()))
            end = first + 15
            if end >= 127 and (end - 127) % 16 == 0:
                pending[round(end / 60.0, 4)] = time.perf_counter()
            await ws.send(encode_binary(0, first, samples[first : first + 16]))
        await ws.send(json.dumps({"type": "stop"}))
        sent.append(len(samples))
        await rx


async def bench_streams(base: str, n: int, seconds: float) -> dict:
    url = base.replace("http", "ws") + "/v1/stream"
    lat: list[float] = []
    sent: list[int] = []
    failures: list[str] = []
    before = _samples_metric(base)
    start_at = time.perf_counter() + 2.0 + n * 0.005
    t = time.perf_counter()
    await asyncio.gather(*[_one_stream(url, seconds, lat, sent, start_at + k * 0.001, failures) for k in range(n)])
    wall = time.perf_counter() - t
    received = _samples_metric(base) - before
    return {
        "streams": n,
        "streams_failed": len(failures),
        "failures": sorted(set(failures))[:5],
        "stream_seconds": seconds,
        "samples_sent": int(sum(sent)),
        "samples_received_by_server": int(received),
        "samples_lost_in_completed_streams": int(sum(sent) - received) if not failures else None,
        "samples_per_s_sustained": received / seconds,
        "result_latency_ms_p50": _pct(lat, 50),
        "result_latency_ms_p99": _pct(lat, 99),
        "results_with_latency": len(lat),
        "wall_s": wall,
    }


def _samples_metric(base: str) -> float:
    for line in httpx.get(f"{base}/metrics").text.splitlines():
        if line.startswith("wearmocap_stream_samples_total "):
            return float(line.split()[1])
    return 0.0


def bench_vs_mlflow(assignment_dir: Path, batch: int, n_batches: int) -> dict:
    """Same ONNX file, same batches: our /v1/imu/windows (assignment only) vs mlflow /invocations."""
    manifest = read_manifest(assignment_dir / "manifest.json")
    with tempfile.TemporaryDirectory() as tmp:
        only = Path(tmp) / "models" / manifest.name / manifest.version
        shutil.copytree(assignment_dir, only)
        mlflow.set_tracking_uri(f"sqlite:///{REPO / 'mlflow.db'}")
        model_dir = Path(mlflow.artifacts.download_artifacts(manifest.mlflow["model_uri"], dst_path=tmp))
        x = _windows(batch)
        ours_body = json.dumps({"windows": [{"samples": w.tolist()} for w in x]})
        theirs_body = json.dumps({"inputs": x.tolist()})
        out = {}
        for name, (proc, base), path, body in (
            ("ours", start_service(Path(tmp) / "models"), "/v1/imu/windows", ours_body),
            ("mlflow_models_serve", start_mlflow_serve(model_dir), "/invocations", theirs_body),
        ):
            try:
                with httpx.Client(timeout=120) as c:
                    headers = {"content-type": "application/json"}
                    c.post(base + path, content=body, headers=headers).raise_for_status()
                    t = time.perf_counter()
                    for _ in range(n_batches):
                        c.post(base + path, content=body, headers=headers).raise_for_status()
                    out[f"{name}_windows_per_s"] = batch * n_batches / (time.perf_counter() - t)
            finally:
                stop(proc)
    out["ratio_ours_over_mlflow"] = out["ours_windows_per_s"] / out["mlflow_models_serve_windows_per_s"]
    out["batch_size"] = batch
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--streams", type=int, nargs="+", default=[50, 100, 200])
    parser.add_argument("--stream-seconds", type=float, default=20.0)
    parser.add_argument("--batch", type=int, default=256)
    parser.add_argument("--batches", type=int, default=20)
    parser.add_argument("--single", type=int, default=300)
    args = parser.parse_args()
    models = REPO / "onnx_models"
    result: dict = {
        "command": "python -m benchmarks.bench_service "
        f"--streams {' '.join(map(str, args.streams))} --stream-seconds {args.stream_seconds} --batch {args.batch}",
        "machine": {"cpus": __import__("os").cpu_count(), "python": platform.python_version()},
        "models": {
            p.parent.name: p.name for p in (_latest(models / "i2s_assignment"), _latest(models / "i2s_alignment"))
        },
    }
    proc, base = start_service(models)
    try:
        result["rest"] = bench_rest(base, args.single, args.batch, args.batches)
        print(json.dumps(result["rest"], indent=2))
        result["streams"] = []
        for n in args.streams:
            result["streams"].append(asyncio.run(bench_streams(base, n, args.stream_seconds)))
            print(json.dumps(result["streams"][-1], indent=2))
    finally:
        stop(proc)
    result["vs_mlflow"] = bench_vs_mlflow(_latest(models / "i2s_assignment"), args.batch, args.batches)
    print(json.dumps(result["vs_mlflow"], indent=2))
    RESULTS.mkdir(parents=True, exist_ok=True)
    (RESULTS / "service.json").write_text(json.dumps(result, indent=2) + "\n")


if __name__ == "__main__":
    main()
