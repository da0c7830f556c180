"""Service benchmark on this machine, all measured in one run and written to benchmarks/results/service.json:

(a) single-window POST latency and batched POST throughput (assignment + alignment), JSON and raw float32;
(b) N concurrent WebSocket streams at 60 Hz: samples/s sustained, result latency p50/p99, samples lost, and how
    many the service refused at its capacity (close code 1013: the admitted ones keep their latency);
(c) the served assignment ONNX file behind our service vs behind ``mlflow models serve``, same batches, as a
    ratio (ours with JSON and with raw float32 bodies; MLflow takes JSON);
(d) time to answer: every real walking recording of the data directory streamed at real time, all at once, one
    session each with all its labelled sensors; per recording the seconds (stream time) from the first moving
    window until the running joint assignment is right and stays right, and until its status is ``assigned``.
    The served model may have trained on these people: the held-out figures are ``training.cli calibrate``'s.

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
import mlflow.onnx
import numpy as np
import onnx
import orjson
import websockets

from benchmarks.machine import machine_state
from benchmarks.servers import REPO, process_cpu_s, start_mlflow_serve, start_service, stop
from service.api.protocol import encode_binary
from service.core.manifest import read_manifest
from service.core.segments import SEGMENTS
from service.core.windowing import HOP_SAMPLES, WINDOW_SAMPLES

RESULTS = REPO / "benchmarks" / "results"
WARMUP_REQUESTS = 200  # steady-state latency: the first requests after start-up pay allocator and cache warm-up
PACKET_SAMPLES = HOP_SAMPLES  # one packet per model hop: every packet completes a window once 128 samples are buffered


def _windows(n: int, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    x = rng.normal(size=(n, 128, 6)).astype(np.float32)
    x[..., 2] += 9.81
    return x


def _pct(values: list[float], q: float) -> float:
    return float(np.percentile(values, q)) if values else float("nan")


def _bodies(x: np.ndarray) -> dict[str, tuple[str, bytes, str]]:
    """The same windows as a JSON body and as a raw float32 body: (path, body, content type)."""
    as_json = json.dumps({"windows": [{"samples": w.tolist()} for w in x]}).encode()
    return {
        "json": ("/v1/imu/windows", as_json, "application/json"),
        "binary": ("/v1/imu/windows/binary", x.astype("<f4").tobytes(), "application/octet-stream"),
    }


def _post_rate(c: httpx.Client, url: str, body: bytes, ctype: str, windows: int, n: int) -> float:
    c.post(url, content=body, headers={"content-type": ctype}).raise_for_status()
    t = time.perf_counter()
    for _ in range(n):
        c.post(url, content=body, headers={"content-type": ctype}).raise_for_status()
    return windows * n / (time.perf_counter() - t)


def bench_rest(base: str, n_single: int, batch: int, n_batches: int) -> dict:
    out: dict = {"batch_size": batch, "client": "httpx, one connection, one request at a time"}
    with httpx.Client(timeout=60) as c:
        for fmt, (path, body, ctype) in _bodies(_windows(1)).items():
            for _ in range(WARMUP_REQUESTS):
                c.post(base + path, content=body, headers={"content-type": ctype}).raise_for_status()
            lat = []
            for _ in range(n_single):
                t = time.perf_counter()
                c.post(base + path, content=body, headers={"content-type": ctype}).raise_for_status()
                lat.append((time.perf_counter() - t) * 1000)
            out[f"single_window_{fmt}_post_ms_p50"] = _pct(lat, 50)
            out[f"single_window_{fmt}_post_ms_p99"] = _pct(lat, 99)
        for fmt, (path, body, ctype) in _bodies(_windows(batch)).items():
            out[f"batched_{fmt}_windows_per_s"] = _post_rate(c, base + path, body, ctype, batch, n_batches)
    return out


class Refused(Exception):
    """The service refused the stream with 1013 (at capacity)."""


async def _one_stream(
    url: str, seconds: float, lat_ms: list[float], sent: list[int], start_at: float, failures: list[str]
) -> None:
    try:
        await _stream_body(url, seconds, lat_ms, sent, start_at)
    except (websockets.ConnectionClosed, OSError, Refused) as exc:
        failures.append(type(exc).__name__ + ": " + str(exc)[:120])


async def _stream_body(url: str, seconds: float, lat_ms: list[float], sent: list[int], start_at: float) -> None:
    x = _windows(1, seed=len(sent))[0]
    samples = np.tile(x, (int(seconds * 60 / 128) + 2, 1))[: int(seconds * 60)]
    pending: dict[float, float] = {}
    async with websockets.connect(url, max_size=2**24, ping_interval=None) as ws:
        await ws.send(json.dumps({"type": "start", "sensors": [{"sensor_id": "s"}]}))
        started = orjson.loads(await ws.recv())
        if started["type"] == "error" and started.get("close_code") == 1013:
            raise Refused(started["detail"])  # admission: the service is at its stream capacity

        async def receive() -> None:
            async for raw in ws:
                if not raw.startswith('{"type":"result"'):  # the client's CPU is this machine's too
                    continue
                m = orjson.loads(raw)
                if m["type"] == "result":
                    t_sent = pending.pop(round(m["window_end_s"], 4), None)
                    if t_sent is not None:
                        lat_ms.append((time.perf_counter() - t_sent) * 1000)

        rx = asyncio.create_task(receive())
        await asyncio.sleep(max(0.0, start_at - time.perf_counter()))
        t0 = time.perf_counter()
        for first in range(0, len(samples), PACKET_SAMPLES):
            due = t0 + (first + PACKET_SAMPLES) / 60.0
            await asyncio.sleep(max(0.0, due - time.perf_counter()))
            end = first + PACKET_SAMPLES - 1  # index of the packet's last sample
            if end >= WINDOW_SAMPLES - 1 and (end - WINDOW_SAMPLES + 1) % HOP_SAMPLES == 0:
                pending[round(end / 60.0, 4)] = time.perf_counter()
            await ws.send(encode_binary(0, first, samples[first : first + PACKET_SAMPLES]))
        await ws.send(json.dumps({"type": "stop"}))
        sent.append(len(samples))
        await rx


async def bench_streams(base: str, n: int, seconds: float, server_pid: int | None = None) -> dict:
    url = base.replace("http", "ws") + "/v1/stream"
    lat: list[float] = []
    sent: list[int] = []
    failures: list[str] = []
    before = _server_metrics(base)
    cpu_before = None if server_pid is None else (process_cpu_s(server_pid), process_cpu_s(server_pid, True))
    client_before = time.process_time()  # the load generator's CPU: this machine's cores are shared
    start_at = time.perf_counter() + 2.0 + n * 0.005
    t = time.perf_counter()
    # Independent sensors: packet phases spread evenly over one packet period (16 samples at 60 Hz).
    phase = PACKET_SAMPLES / 60.0 / n
    await asyncio.gather(*[_one_stream(url, seconds, lat, sent, start_at + k * phase, failures) for k in range(n)])
    wall = time.perf_counter() - t
    server = {k: v - before.get(k, 0.0) for k, v in _server_metrics(base).items()}
    cpu_after = None if server_pid is None else (process_cpu_s(server_pid), process_cpu_s(server_pid, True))
    client_cpu_s = time.process_time() - client_before
    windows = server["wearmocap_inference_batch_windows_sum"]
    received = server["wearmocap_stream_samples_total"]
    refused = sum(f.startswith("Refused") for f in failures)
    failures = [f for f in failures if not f.startswith("Refused")]
    return {
        "streams": n,
        "streams_refused_at_capacity": refused,
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
        "server_mean_packet_to_result_ms": 1000
        * server["wearmocap_stream_result_seconds_sum"]
        / max(server["wearmocap_stream_result_seconds_count"], 1),
        "server_mean_batch_windows": server["wearmocap_inference_batch_windows_sum"]
        / max(server["wearmocap_inference_batch_windows_count"], 1),
        "server_inference_busy_fraction": server["wearmocap_inference_seconds_sum"] / wall,
        # the server process' CPU per window it answered: all of it (event loop, inference threads), and its event
        # loop's thread alone (parsing, windowing, the messages; not inference)
        "server_cpu_ms_per_window": _per_window(cpu_before, cpu_after, 0, windows),
        "server_loop_cpu_ms_per_window": _per_window(cpu_before, cpu_after, 1, windows),
        "client_cpu_ms_per_window": 1000 * client_cpu_s / windows if windows else None,
        "wall_s": wall,
    }


async def answer_session(url: str, recording, seconds: float, start_at: float) -> dict:
    """Stream one labelled recording at real time; the stream time of every ``assignment`` message (the newest
    window end among the results before it), whether it was right, and its status."""
    sensors = [s for s in recording.sensors if s.segment is not None]
    truth = {s.sensor_id: SEGMENTS[s.segment] for s in sensors}
    n = min(int(seconds * 60), min(len(s.imu) for s in sensors))
    answers: list[tuple[float, bool, str]] = []
    state = {"newest": 0.0, "first_moving": None}
    async with websockets.connect(url, max_size=2**24, ping_interval=None) as ws:
        await ws.send(json.dumps({"type": "start", "sensors": [{"sensor_id": s.sensor_id} for s in sensors]}))
        started = orjson.loads(await ws.recv())
        if started["type"] == "error":
            return {"refused": started["detail"]}

        async def receive() -> None:
            async for raw in ws:
                m = orjson.loads(raw)
                if m["type"] == "result":
                    state["newest"] = max(state["newest"], m["window_end_s"])
                    if m["moving"] and state["first_moving"] is None:
                        state["first_moving"] = m["window_end_s"]
                elif m["type"] == "assignment":
                    right = all(a["segment"] == truth[a["sensor_id"]] for a in m["sensors"])
                    answers.append((state["newest"], right, m["status"]))

        rx = asyncio.create_task(receive())
        await asyncio.sleep(max(0.0, start_at - time.perf_counter()))
        t0 = time.perf_counter()
        for first in range(0, n - PACKET_SAMPLES + 1, PACKET_SAMPLES):
            await asyncio.sleep(max(0.0, t0 + (first + PACKET_SAMPLES) / 60.0 - time.perf_counter()))
            for k, s in enumerate(sensors):
                await ws.send(encode_binary(k, first, s.imu[first : first + PACKET_SAMPLES].astype(np.float32)))
        await ws.send(json.dumps({"type": "stop"}))
        await rx
    t_first = state["first_moving"]
    if t_first is None or not answers:
        return {"sensors": len(sensors), "no_moving_window": True}
    wrong = [t for t, right, _ in answers if not right]
    committed = [(t, right) for t, right, status in answers if status == "assigned"]
    settled = max(wrong) if wrong else None
    later = [t for t, _, _ in answers if settled is None or t > settled]
    return {
        "sensors": len(sensors),
        "streamed_s": n / 60.0,
        # 0 where it is right for good from a message before the first moving window
        "right_s": max(0.0, later[0] - t_first if settled is not None else answers[0][0] - t_first) if later else None,
        "committed_s": committed[0][0] - t_first if committed else None,
        "committed_right": committed[0][1] if committed else None,
    }


async def bench_time_to_answer(base: str, seconds: float, concurrency: int) -> dict:
    from service.core.recordings import read_all_real
    from training.data.catalog import resolve_data_dir

    walking = [r for r in read_all_real(resolve_data_dir(None)) if r.activity.startswith(("walk", "stairs"))]
    url = base.replace("http", "ws") + "/v1/stream"
    gate = asyncio.Semaphore(concurrency)  # sessions at once: one machine's worth, the rest wait their turn

    async def one(k: int, recording) -> dict:
        async with gate:
            return await answer_session(url, recording, seconds, time.perf_counter() + k % concurrency * 0.01)

    runs = await asyncio.gather(*[one(k, r) for k, r in enumerate(walking)])
    per = {r.name: run for r, run in zip(walking, runs, strict=True)}
    ran = [v for v in per.values() if "right_s" in v]
    right = [v["right_s"] for v in ran if v["right_s"] is not None]
    committed = [v["committed_s"] for v in ran if v["committed_s"] is not None]
    return {
        "recordings": len(per),
        "sessions_at_once": concurrency,
        "refused_at_capacity": sum("refused" in v for v in per.values()),
        "sensor_streams": sum(v.get("sensors", 0) for v in per.values()),
        "seconds_streamed_per_recording": seconds,
        "right_for_good_s_median": _pct(right, 50),
        "right_for_good_s_worst": max(right, default=float("nan")),
        "never_right_for_good": sum(v["right_s"] is None for v in ran),
        "committed_s_median": _pct(committed, 50),
        "committed_s_worst": max(committed, default=float("nan")),
        "never_committed": sum(v["committed_s"] is None for v in ran),
        "committed_wrong": sum(v["committed_right"] is False for v in ran),
        "per_recording": per,
    }


def _per_window(before: tuple | None, after: tuple | None, k: int, windows: float) -> float | None:
    if before is None or after is None or before[k] is None or after[k] is None or not windows:
        return None
    return 1000 * (after[k] - before[k]) / windows


def summarize_streams(runs: list[dict]) -> dict:
    """Repeated runs of one stream count: this machine's timing noise is large, so every run is kept."""
    p99 = [r["result_latency_ms_p99"] for r in runs]
    lost = [r["samples_lost_in_completed_streams"] for r in runs]
    return {
        "streams": runs[0]["streams"],
        "runs": len(runs),
        "samples_lost_per_run": lost,
        "streams_failed_per_run": [r["streams_failed"] for r in runs],
        "streams_refused_at_capacity_per_run": [r["streams_refused_at_capacity"] for r in runs],
        "result_latency_ms_p50_per_run": [r["result_latency_ms_p50"] for r in runs],
        "result_latency_ms_p99_per_run": p99,
        "result_latency_ms_p99_median_of_runs": float(np.median(p99)),
        "server_cpu_ms_per_window_per_run": [r["server_cpu_ms_per_window"] for r in runs],
        "server_loop_cpu_ms_per_window_per_run": [r["server_loop_cpu_ms_per_window"] for r in runs],
        "client_cpu_ms_per_window_per_run": [r["client_cpu_ms_per_window"] for r in runs],
        "details": runs,
    }


SERVER_METRICS = (
    "wearmocap_stream_samples_total",
    "wearmocap_stream_result_seconds_sum",
    "wearmocap_stream_result_seconds_count",
    "wearmocap_inference_batch_windows_sum",
    "wearmocap_inference_batch_windows_count",
    "wearmocap_inference_seconds_sum",
)


def _server_metrics(base: str) -> dict[str, float]:
    values = {}
    for line in httpx.get(f"{base}/metrics").text.splitlines():
        name, _, value = line.partition(" ")
        if name in SERVER_METRICS:
            values[name] = float(value)
    return values


def bench_vs_mlflow(model_dir: Path, batch: int, n_batches: int) -> dict:
    """One ONNX file behind our service (assignment only) and behind ``mlflow models serve``, same windows.

    MLflow's scoring server takes JSON (or CSV) only, so it gets ``{"inputs": ...}``; ours is measured with
    its JSON body and with its raw float32 body.
    """
    manifest = read_manifest(model_dir / "manifest.json")
    with tempfile.TemporaryDirectory() as tmp:
        ours_root = Path(tmp) / "models"
        shutil.copytree(model_dir, ours_root / manifest.name / manifest.version)
        mlflow_dir = Path(tmp) / "mlflow_model"
        x = _windows(batch)
        mlflow.onnx.save_model(onnx.load(str(model_dir / "model.onnx")), str(mlflow_dir), input_example=x[:1])
        out: dict = {"model": str(model_dir.relative_to(REPO)), "batch_size": batch}
        proc, base = start_service(ours_root)
        try:
            with httpx.Client(timeout=120) as c:
                for fmt, (path, body, ctype) in _bodies(x).items():
                    out[f"ours_{fmt}_windows_per_s"] = _post_rate(c, base + path, body, ctype, batch, n_batches)
        finally:
            stop(proc)
        proc, base = start_mlflow_serve(mlflow_dir)
        try:
            with httpx.Client(timeout=120) as c:
                body = json.dumps({"inputs": x.tolist()}).encode()
                out["mlflow_models_serve_json_windows_per_s"] = _post_rate(
                    c, base + "/invocations", body, "application/json", batch, n_batches
                )
        finally:
            stop(proc)
    theirs = out["mlflow_models_serve_json_windows_per_s"]
    out["ratio_ours_json_over_mlflow"] = out["ours_json_windows_per_s"] / theirs
    out["ratio_ours_binary_over_mlflow"] = out["ours_binary_windows_per_s"] / theirs
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--streams", type=int, nargs="+", default=[50, 100, 200])
    parser.add_argument("--stream-seconds", type=float, default=20.0)
    parser.add_argument("--repeats", type=int, default=3, help="runs per stream count")
    parser.add_argument("--batch", type=int, default=256)
    parser.add_argument("--batches", type=int, default=20)
    parser.add_argument("--single", type=int, default=300)
    parser.add_argument(
        "--parts",
        nargs="+",
        choices=["rest", "streams", "mlflow", "answer"],
        default=["rest", "streams", "mlflow", "answer"],
    )
    parser.add_argument("--answer-seconds", type=float, default=45.0, help="seconds of each recording (d)")
    parser.add_argument("--answer-sessions", type=int, default=8, help="recordings streamed at once (d)")
    parser.add_argument("--out", type=Path, default=RESULTS / "service.json")
    args = parser.parse_args()
    models = REPO / "onnx_models"
    result: dict = {
        "command": "python -m benchmarks.bench_service "
        f"--streams {' '.join(map(str, args.streams))} --stream-seconds {args.stream_seconds} "
        f"--repeats {args.repeats} --batch {args.batch} --parts {' '.join(args.parts)}"
        f" --answer-seconds {args.answer_seconds} --answer-sessions {args.answer_sessions}",
        "machine": {"cpus": __import__("os").cpu_count(), "python": platform.python_version()},
        "machine_state": [machine_state(models, "start")],  # how fast the machine ran (benchmarks/machine.py)
    }
    print(json.dumps(result["machine_state"][0]))
    proc, base = start_service(models)
    try:
        # what the server serves (the newest files, or the WEARMOCAP_MODEL_VERSIONS pins of this environment)
        result["models"] = {name: m["version"] for name, m in httpx.get(f"{base}/v1/models").json().items()}
        if "rest" in args.parts:
            result["rest"] = bench_rest(base, args.single, args.batch, args.batches)
            print(json.dumps(result["rest"], indent=2))
        result["streams"] = []
        for n in args.streams if "streams" in args.parts else []:
            runs = []
            for _ in range(args.repeats):
                runs.append(asyncio.run(bench_streams(base, n, args.stream_seconds, proc.pid)))
                print(json.dumps({k: v for k, v in runs[-1].items() if k != "failures"}))
            result["streams"].append(summarize_streams(runs))
        if "answer" in args.parts:
            result["time_to_answer"] = asyncio.run(
                bench_time_to_answer(base, args.answer_seconds, args.answer_sessions)
            )
            print(json.dumps({k: v for k, v in result["time_to_answer"].items() if k != "per_recording"}, indent=2))
    finally:
        stop(proc)
    if "mlflow" in args.parts:  # the served assignment file, as the README quotes it
        served = models / "i2s_assignment" / result["models"]["i2s_assignment"]
        result["vs_mlflow"] = [bench_vs_mlflow(served, args.batch, args.batches)]
        print(json.dumps(result["vs_mlflow"], indent=2))
    result["machine_state"].append(machine_state(models, "end"))
    print(json.dumps(result["machine_state"][1]))
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(result, indent=2) + "\n")


if __name__ == "__main__":
    main()
