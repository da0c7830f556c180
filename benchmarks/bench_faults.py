"""Fault benchmark against a real uvicorn server with the served models, written to benchmarks/results/faults.json:

(a) chunked bodies of 100 MB and 500 MB (Transfer-Encoding: chunked, no Content-Length): the answer and the server's
    peak RSS growth (VmHWM) for each (goal: ≤ 100 MB);
(b) 1,000 concurrent single-window POSTs: how many were answered 200 and their latency against the deadline, how
    many got 503 with Retry-After and how fast (goal: every 200 within the deadline, every 503 in ≤ 100 ms);
(c) a single window's latency, one POST after another, while a 4,096-window binary batch runs (goal: p99 ≤ 250 ms);
(d) 50 WebSocket consumers that never read (each on a socket with a 4 KiB receive buffer, a slow link, sending a
    six-sensor 60 Hz suit in real time) for 60 s beside one healthy 60 Hz stream: the server's RSS growth, the healthy
    stream's result latency, and the close code and reason each slow consumer finds when it reads at the end
    (goal: RSS growth ≤ 50 MB, healthy p99 ≤ 100 ms, every slow consumer closed with a reason).

    python -m benchmarks.bench_faults
"""

from __future__ import annotations

import argparse
import asyncio
import json
import os
import platform
import selectors
import socket
import time
from pathlib import Path

import httpx
import websockets

from benchmarks.bench_service import _pct, _stream_body, _windows
from benchmarks.servers import REPO, start_service, stop
from service.api.protocol import encode_binary
from service.core.windowing import HOP_SAMPLES

RESULTS = REPO / "benchmarks" / "results"
SUIT_SENSORS = 6


def vm_mib(pid: int, field: str) -> float:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith(field + ":"):
            return int(line.split()[1]) / 1024
    raise KeyError(field)


async def _request(port: int, raw: bytes, timeout_s: float = 120.0) -> tuple[int, float, dict[str, str]]:
    """One HTTP/1.1 request on its own connection: (status, seconds from sending it to the whole answer, headers)."""
    reader, writer = await asyncio.open_connection("127.0.0.1", port)
    try:
        return await _exchange(reader, writer, raw, timeout_s)
    finally:
        writer.close()


async def _exchange(
    reader: asyncio.StreamReader, writer: asyncio.StreamWriter, raw: bytes, timeout_s: float = 120.0
) -> tuple[int, float, dict[str, str]]:
    start = time.perf_counter()
    writer.write(raw)
    await writer.drain()
    head = await asyncio.wait_for(reader.readuntil(b"\r\n\r\n"), timeout_s)
    lines = head.decode("latin-1").split("\r\n")
    headers = {k.lower(): v.strip() for k, _, v in (line.partition(":") for line in lines[1:] if line)}
    await reader.readexactly(int(headers.get("content-length", 0)))
    return int(lines[0].split()[1]), time.perf_counter() - start, headers


def _post(path: str, body: bytes, ctype: str = "application/json") -> bytes:
    head = f"POST {path} HTTP/1.1\r\nHost: bench\r\nContent-Type: {ctype}\r\nContent-Length: {len(body)}\r\n\r\n"
    return head.encode() + body


def chunked_post(port: int, path: str, total_bytes: int, chunk: int = 1 << 20) -> tuple[int | None, bytes, int]:
    """POST ``total_bytes`` of a JSON-looking body with Transfer-Encoding: chunked (no Content-Length): the answer's
    status and body, and the bytes sent before the server stopped reading (or all of them)."""
    sock = socket.create_connection(("127.0.0.1", port))
    sock.sendall(
        f"POST {path} HTTP/1.1\r\nHost: bench\r\nContent-Type: application/json\r\n".encode()
        + b"Transfer-Encoding: chunked\r\n\r\n"
    )
    piece = b"[" + b"0.0," * (chunk // 4 - 1) + b"0]"
    sent = 0
    try:
        while sent < total_bytes:
            sock.sendall(f"{len(piece):x}\r\n".encode() + piece + b"\r\n")
            sent += len(piece)
        sock.sendall(b"0\r\n\r\n")
    except (BrokenPipeError, ConnectionResetError):
        pass
    sock.settimeout(30)
    answer = b""
    try:
        while b"\r\n\r\n" not in answer or len(answer.split(b"\r\n\r\n", 1)[1]) < _content_length(answer):
            data = sock.recv(65536)
            if not data:
                break
            answer += data
    except (ConnectionResetError, TimeoutError):
        pass
    finally:
        sock.close()
    head, _, body = answer.partition(b"\r\n\r\n")
    return (int(head.split()[1]) if head.startswith(b"HTTP/") else None), body, sent


def _content_length(answer: bytes) -> int:
    for line in answer.split(b"\r\n\r\n", 1)[0].split(b"\r\n"):
        if line.lower().startswith(b"content-length:"):
            return int(line.split(b":")[1])
    return 0


def chunked_bodies(pid: int, port: int, sizes_mb: list[int]) -> list[dict]:
    out = []
    for size in sizes_mb:
        before = vm_mib(pid, "VmHWM")
        start = time.perf_counter()
        status, _, sent = chunked_post(port, "/v1/imu/windows", size << 20)
        out.append(
            {
                "body_mb": size,
                "bytes_sent_before_the_server_stopped_reading": sent,
                "status": status,
                "seconds": time.perf_counter() - start,
                "peak_rss_growth_mb": vm_mib(pid, "VmHWM") - before,
                "goal_peak_rss_growth_mb": 100,
            }
        )
        print(json.dumps(out[-1]))
    return out


def _burst(port: int, raw: bytes, n: int, timeout_s: float = 60.0) -> list[tuple[int, float, bool]]:
    """``n`` requests outstanding at once: ``n`` connections opened first (as a load balancer's kept-alive ones), then
    every request written in one tight loop and the answers read as they come (epoll), so that the figures are the
    service's and not this client's. A GET /health storm on 1,000 new connections takes 0.4-0.5 s at the median
    here, whatever the route does; an asyncio client adds tens of milliseconds of its own.
    Returns (status, seconds from write to answer, has Retry-After) per request."""
    socks = [socket.create_connection(("127.0.0.1", port)) for _ in range(n)]
    selector = selectors.DefaultSelector()
    sent, buffers, out = {}, {}, []
    try:
        for s in socks:
            s.setblocking(False)
            selector.register(s, selectors.EVENT_READ)
        for s in socks:
            sent[s] = time.perf_counter()
            s.sendall(raw)
            buffers[s] = b""
        deadline = time.perf_counter() + timeout_s
        while len(out) < n and time.perf_counter() < deadline:
            for key, _ in selector.select(timeout=1.0):
                s = key.fileobj
                chunk = s.recv(65536)
                buffers[s] += chunk
                head, sep, body = buffers[s].partition(b"\r\n\r\n")
                if not sep:
                    continue
                lines = head.decode("latin-1").split("\r\n")
                headers = {k.lower(): v.strip() for k, _, v in (line.partition(":") for line in lines[1:] if line)}
                if len(body) >= int(headers.get("content-length", 0)) or not chunk:
                    out.append((int(lines[0].split()[1]), time.perf_counter() - sent[s], "retry-after" in headers))
                    selector.unregister(s)
    finally:
        for s in socks:
            s.close()
    return out


def concurrent_singles(port: int, n: int, deadline_s: float) -> dict:
    body = _post("/v1/imu/windows", json.dumps({"windows": [{"samples": _windows(1)[0].round(4).tolist()}]}).encode())
    results = _burst(port, body, n)
    ok = [t for status, t, _ in results if status == 200]
    shed = [(t, retry) for status, t, retry in results if status == 503]
    shed_s = [t for t, _ in shed]
    return {
        "requests": n,
        "answers": len(results),
        "deadline_s": deadline_s,
        "answered_200": len(ok),
        "answered_200_latency_s_p50": _pct(ok, 50),
        "answered_200_latency_s_max": max(ok, default=float("nan")),
        "answered_200_within_deadline": sum(t <= deadline_s for t in ok),
        "shed_503": len(shed),
        "shed_503_with_retry_after": sum(retry for _, retry in shed),
        "shed_503_latency_ms_p50": 1000 * _pct(shed_s, 50),
        "shed_503_latency_ms_p99": 1000 * _pct(shed_s, 99),
        "shed_503_latency_ms_max": 1000 * max(shed_s, default=float("nan")),
        "shed_503_within_100_ms": sum(t <= 0.1 for t in shed_s),
        "other_statuses": sorted({status for status, _, _ in results} - {200, 503}),
    }


async def single_during_batch(port: int, batch: int) -> dict:
    big = _post("/v1/imu/windows/binary", _windows(batch).astype("<f4").tobytes(), "application/octet-stream")
    one = _post("/v1/imu/windows", json.dumps({"windows": [{"samples": _windows(1, 1)[0].round(4).tolist()}]}).encode())
    batch_task = asyncio.ensure_future(_request(port, big, timeout_s=600))
    await asyncio.sleep(0.2)
    lat, statuses = [], []
    while not batch_task.done():
        status, seconds, _ = await _request(port, one)
        statuses.append(status)
        lat.append(seconds * 1000)
        await asyncio.sleep(0.02)
    batch_status, batch_s, _ = batch_task.result()
    return {
        "batch_windows": batch,
        "batch_status": batch_status,
        "batch_seconds": batch_s,
        "single_requests": len(lat),
        "single_statuses": sorted(set(statuses)),
        "single_latency_ms_p50": _pct(lat, 50),
        "single_latency_ms_p99": _pct(lat, 99),
        "single_latency_ms_max": max(lat, default=float("nan")),
        "goal_single_latency_ms_p99": 250,
    }


async def _slow_consumer(url: str, seconds: float, k: int) -> dict:
    """A six-sensor suit at 60 Hz sent in real time on a socket with a 4 KiB receive buffer; reads nothing until the
    end."""
    host, port = url.split("//")[1].split("/")[0].split(":")
    sock = socket.socket()
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)
    sock.connect((host, int(port)))
    x = _windows(1, seed=100 + k)[0]
    out: dict = {"received": 0}
    try:
        async with websockets.connect(url, sock=sock, max_queue=1, ping_interval=None) as ws:
            sensors = [{"sensor_id": f"slow{k}_{s}"} for s in range(SUIT_SENSORS)]
            await ws.send(json.dumps({"type": "start", "sensors": sensors}))
            t0, seq = time.perf_counter(), 0
            await asyncio.sleep(k * HOP_SAMPLES / 60.0 / 50)
            try:
                while time.perf_counter() - t0 < seconds:
                    packet = x[seq % 112 : seq % 112 + HOP_SAMPLES]
                    for s in range(SUIT_SENSORS):
                        await asyncio.wait_for(ws.send(encode_binary(s, seq, packet)), 2)
                    seq += HOP_SAMPLES
                    await asyncio.sleep(max(0.0, t0 + seq / 60.0 - time.perf_counter()))
            except (websockets.ConnectionClosed, TimeoutError):
                pass
            while True:  # read what is there: the queued messages, then the close frame
                await asyncio.wait_for(ws.recv(), 30)
                out["received"] += 1
    except websockets.ConnectionClosed as exc:
        out["close_code"] = exc.rcvd.code if exc.rcvd else None
        out["close_reason"] = exc.rcvd.reason if exc.rcvd else None
    except (TimeoutError, OSError) as exc:
        out["error"] = type(exc).__name__
    return out


async def slow_consumers(base: str, pid: int, n: int, seconds: float) -> dict:
    url = base.replace("http", "ws") + "/v1/stream"
    rss_before = vm_mib(pid, "VmRSS")
    lat: list[float] = []
    sent: list[int] = []
    healthy = asyncio.ensure_future(_stream_body(url, seconds, lat, sent, time.perf_counter() + 1.0))
    await asyncio.sleep(0.5)  # the healthy stream is admitted first
    peak = [rss_before]

    async def watch_rss() -> None:
        while not healthy.done():
            peak.append(vm_mib(pid, "VmRSS"))
            await asyncio.sleep(0.5)

    watcher = asyncio.ensure_future(watch_rss())
    slow = await asyncio.gather(*(_slow_consumer(url, seconds, k) for k in range(n)))
    await healthy
    await watcher
    reasons: dict[str, int] = {}
    for s in slow:
        key = f"{s.get('close_code')} {str(s.get('close_reason') or s.get('error'))[:40]}"
        reasons[key] = reasons.get(key, 0) + 1
    return {
        "slow_consumers": n,
        "seconds": seconds,
        "rss_growth_mb_peak": max(peak) - rss_before,
        "healthy_results": len(lat),
        "healthy_latency_ms_p50": _pct(lat, 50),
        "healthy_latency_ms_p99": _pct(lat, 99),
        "slow_closed_with_reason": sum(bool(s.get("close_reason")) for s in slow),
        "slow_close_kinds": reasons,
        "goals": {"rss_growth_mb": 50, "healthy_latency_ms_p99": 100},
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument(
        "--parts",
        nargs="+",
        choices=["bodies", "singles", "batch", "streams"],
        default=["bodies", "singles", "batch", "streams"],
    )
    parser.add_argument("--body-mb", type=int, nargs="+", default=[100, 500])
    parser.add_argument("--singles", type=int, default=1000)
    parser.add_argument("--batch", type=int, default=4096)
    parser.add_argument("--slow", type=int, default=50)
    parser.add_argument("--stream-seconds", type=float, default=60.0)
    parser.add_argument("--out", type=Path, default=RESULTS / "faults.json")
    args = parser.parse_args()
    result: dict = {
        "command": "python -m benchmarks.bench_faults " + " ".join(os.sys.argv[1:]),
        "machine": {"cpus": os.cpu_count(), "python": platform.python_version()},
    }
    proc, base = start_service(REPO / "onnx_models")
    port = int(base.rsplit(":", 1)[1])
    try:
        result["models"] = {name: m["version"] for name, m in httpx.get(f"{base}/v1/models").json().items()}
        result["settings"] = {"request_deadline_s": 2.0, "max_body_bytes": 32 << 20}  # the defaults
        if "bodies" in args.parts:
            result["chunked_bodies"] = chunked_bodies(proc.pid, port, args.body_mb)
        if "singles" in args.parts:
            result["concurrent_singles"] = concurrent_singles(port, args.singles, 2.0)
            print(json.dumps(result["concurrent_singles"]))
            time.sleep(3)
        if "batch" in args.parts:
            result["single_during_batch"] = asyncio.run(single_during_batch(port, args.batch))
            print(json.dumps(result["single_during_batch"]))
        if "streams" in args.parts:
            result["slow_consumers"] = asyncio.run(slow_consumers(base, proc.pid, args.slow, args.stream_seconds))
            print(json.dumps(result["slow_consumers"]))
        metrics = httpx.get(f"{base}/metrics").text.splitlines()
        result["server_metrics"] = [
            line
            for line in metrics
            if line.startswith(("wearmocap_streams", "wearmocap_requests_shed", "wearmocap_capacity"))
        ]
    finally:
        stop(proc)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(result, indent=2) + "\n")


if __name__ == "__main__":
    main()
