"""What one client can cost the service: body size on the bytes received, error size, load shedding with
Retry-After, dropped work of clients that left, and the key, metrics and origin settings."""

from __future__ import annotations

import asyncio
import json
import time
from pathlib import Path

import httpx
import numpy as np
import pytest
from fastapi.testclient import TestClient

from benchmarks.bench_faults import chunked_post, vm_mib
from benchmarks.servers import start_service, stop
from service.app import create_app
from service.settings import Settings

WINDOW = {"samples": [[0.0, 0.0, 9.81, 0.5, 0.0, 0.0]] * 128}


def test_a_chunked_body_over_the_limit_is_413_and_never_held(tiny_models: Path) -> None:
    server, base = start_service(tiny_models, max_body_bytes="1000000")
    try:
        port = int(base.rsplit(":", 1)[1])
        before = vm_mib(server.pid, "VmHWM")
        status, body, _ = chunked_post(port, "/v1/imu/windows", 200 << 20)  # 200 MB, 200× the limit
        grown_mib = vm_mib(server.pid, "VmHWM") - before
        assert status == 413, body[:300]
        assert "exceeds the limit of 1000000 bytes" in json.loads(body)["detail"]
        assert grown_mib < 20, f"peak RSS grew {grown_mib:.0f} MiB for a 200 MB body"
        # Within the limit, chunked works as before.
        body = iter([json.dumps({"windows": [WINDOW]}).encode()])
        ok = httpx.post(f"{base}/v1/imu/windows", content=body, headers={"content-type": "application/json"})
        assert ok.status_code == 200, ok.text
    finally:
        stop(server)


def test_an_invalid_body_gets_a_bounded_error_in_one_shape(client: TestClient) -> None:
    bad = {"windows": [{"samples": [["x"] * 6] * 128}] * 200}  # 153,600 wrong values, a 1.2 MB body
    r = client.post("/v1/imu/windows", json=bad)
    assert r.status_code == 422
    body = r.json()
    assert set(body) == {"detail", "errors", "errors_total"} and isinstance(body["detail"], str)
    assert len(body["errors"]) == 20 and body["errors_total"] == 153_600
    assert len(r.content) < 10_000
    assert all(e["input"] is None or len(e["input"]) <= 230 for e in body["errors"])
    # A whole wrong body is quoted as an excerpt, not echoed.
    r = client.post("/v1/imu/windows", json={"windowz": "y" * 500_000})
    assert r.status_code == 422 and len(r.content) < 5_000, len(r.content)
    assert "characters)" in r.text
    # Other errors have the same shape.
    r = client.post("/v1/imu/assign", json={"sensors": [{"sensor_id": "a", "windows": [WINDOW]}] * 2})
    assert r.status_code == 422 and isinstance(r.json()["detail"], str) and "unique" in r.json()["detail"]


def test_requests_beyond_the_deadline_are_shed_at_once_with_retry_after(tiny_models: Path) -> None:
    settings = Settings(models_dir=tiny_models, capacity_windows_per_s=10.0, request_deadline_s=0.5)
    with TestClient(create_app(settings)) as c:
        batcher = c.app.state.batcher
        assert batcher.capacity_windows_per_s == pytest.approx(10.0)
        batcher.reserved = 20  # 2 s of work admitted ahead (bodies being read)
        start = time.monotonic()
        r = c.post("/v1/imu/windows", json={"windows": [WINDOW]})
        assert r.status_code == 503 and time.monotonic() - start < 0.1
        assert int(r.headers["Retry-After"]) == 2  # ceil(2.1 - 0.5)
        assert "overloaded" in r.json()["detail"]
        assert c.post("/v1/pose/imu", json={}).status_code == 503  # every /v1 POST is shed the same way
        batcher.reserved = 0
        assert c.post("/v1/imu/windows", json={"windows": [WINDOW]}).status_code == 200
        metrics = c.get("/metrics").text
        assert "wearmocap_requests_shed_total 2.0" in metrics
        assert "wearmocap_capacity_windows_per_second 10.0" in metrics


def test_the_work_of_a_client_that_gave_up_is_dropped(tiny_models: Path) -> None:
    # A slow service (capacity forced to 5 windows/s against a deadline of 60 s) and clients that give up after
    # 0.3 s: their queued windows are never computed.
    server, base = start_service(
        tiny_models,
        capacity_windows_per_s="5",
        request_deadline_s="60",
        inference_chunk_windows="1",
        inference_threads="1",
    )
    try:

        async def main() -> None:
            async with httpx.AsyncClient(timeout=0.3) as http:
                # Each binary body of 64 zero windows; the tiny models are fast, so the dispatcher is slowed by the
                # 64 turns only: give up before they are through.
                body = np.zeros((2048, 128, 6), "<f4").tobytes()
                results = await asyncio.gather(
                    *(http.post(f"{base}/v1/imu/windows/binary", content=body) for _ in range(4)),
                    return_exceptions=True,
                )
                assert any(isinstance(r, httpx.TimeoutException) for r in results), results

        asyncio.run(main())
        time.sleep(1.0)
        metrics = httpx.get(f"{base}/metrics").text
        assert 'status="499"' in metrics, [line for line in metrics.splitlines() if "requests_total" in line]
    finally:
        stop(server)


def test_the_key_guards_metrics_when_asked_and_origins_are_checked(tiny_models: Path) -> None:
    settings = Settings(
        models_dir=tiny_models, api_key="k" * 32, metrics_require_key=True, allowed_origins="https://lab.example.org"
    )
    with TestClient(create_app(settings)) as c:
        assert c.get("/metrics").status_code == 401
        assert c.get("/metrics", headers={"X-API-Key": "k" * 32}).status_code == 200
        assert c.get("/metrics", headers={"X-API-Key": "k" * 31 + "j"}).status_code == 401
        assert c.get("/health").status_code == 200 and c.get("/ready").status_code == 200
        pre = c.options(
            "/v1/imu/windows",
            headers={"Origin": "https://lab.example.org", "Access-Control-Request-Method": "POST"},
        )
        assert pre.headers["access-control-allow-origin"] == "https://lab.example.org"
        other = c.options(
            "/v1/imu/windows", headers={"Origin": "https://evil.example", "Access-Control-Request-Method": "POST"}
        )
        assert "access-control-allow-origin" not in other.headers


def test_the_wait_of_small_requests_is_the_pending_ones_times_the_seconds_between_answers() -> None:
    """Answers come in clumps (one inference batch answers many requests at once): the estimate averages the busy
    time between answers over many of them; refusals and errors say nothing of the cost and are left out."""
    from service.api.request_cost import Completions

    c = Completions()
    assert c.wait_s() == 0.0  # nothing measured yet
    for _ in range(3):
        c.started()
    t0 = time.perf_counter() - 0.030
    c.ended(t0, answered=True)  # 30 ms of work
    c.ended(t0, answered=True)  # in the same batch: a gap of about 0
    assert c.seconds_per_request == pytest.approx(0.015, abs=0.002)
    c.ended(time.perf_counter() - 5.0, answered=False)  # a 503 after 5 s: not a measure of the work
    assert c.pending == 0 and c.seconds_per_request == pytest.approx(0.015, abs=0.002)
    c.started()
    assert c.wait_s() == pytest.approx(2 * 0.015, abs=0.004)  # the one pending and the one asking


def test_a_browser_gives_the_key_as_a_websocket_subprotocol(tiny_models: Path) -> None:
    """A browser cannot set X-API-Key on a WebSocket: ``wearmocap.key.<key in base64url>`` carries it, echoed back
    on acceptance; a wrong one is closed with 1008 and the reason, like a wrong header."""
    import base64

    from starlette.websockets import WebSocketDisconnect

    key = "k" * 31 + "+/"  # characters that base64url must carry
    settings = Settings(models_dir=tiny_models, api_key=key)

    def protocol(k: str) -> str:
        return "wearmocap.key." + base64.urlsafe_b64encode(k.encode()).decode().rstrip("=")

    with TestClient(create_app(settings)) as c:
        with c.websocket_connect("/v1/stream", subprotocols=["other", protocol(key)]) as ws:
            assert ws.accepted_subprotocol == protocol(key)
            ws.send_text(json.dumps({"type": "start", "sensors": [{"sensor_id": "a"}]}))
            assert ws.receive_json()["type"] == "started"
        with c.websocket_connect("/v1/stream", subprotocols=[protocol("wrong")]) as ws:
            assert "wearmocap.key. subprotocol" in ws.receive_json()["detail"]
            with pytest.raises(WebSocketDisconnect) as closed:
                ws.receive_json()
            assert closed.value.code == 1008
