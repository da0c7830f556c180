"""The shipped flex models through a real uvicorn server: REST blocks and WebSocket streams answer the same,
on simulated suit readings from real CMU motion and on the real capacitive sleeves."""

from __future__ import annotations

import asyncio
import json
from pathlib import Path

import httpx
import numpy as np
import pytest
import websockets

from benchmarks.servers import REPO, start_service, stop
from service.api.protocol import encode_binary
from service.core.flex import FLEX_SENSOR_JOINTS, bend_angles_deg
from service.core.recordings import read_capacitive_sleeve

SUIT, SLEEVE = "flex_bilstm_cm", "flex_capacitive_knee"


@pytest.fixture(scope="module")
def server():
    proc, base = start_service(REPO / "onnx_models")
    yield base
    stop(proc)


def _suit_readings(data_dir: Path) -> np.ndarray:
    """CMU motion (the largest iClone clip, at most 30 s of it) read by one simulated suit at 20 Hz (the simulator
    of the shipped model)."""
    from training.flex.simulate import draw_suit, simulate_counts
    from training.pose.data import load_motion

    path = max((data_dir / "mocap" / "cmu_iclone").rglob("*.bvh*"), key=lambda p: p.stat().st_size)
    motion = load_motion(path, "cmu_iclone")
    bend = bend_angles_deg(motion.R_world_segment[: 60 * 30 : 3], FLEX_SENSOR_JOINTS)
    return simulate_counts(bend, draw_suit(np.random.default_rng(0), 4), np.random.default_rng(1))


async def _stream(base: str, start: dict, x: np.ndarray, packet: int) -> tuple[dict, list[dict]]:
    async with websockets.connect(base.replace("http", "ws") + "/v1/stream/flex", max_size=None) as ws:
        await ws.send(json.dumps(start))
        started = json.loads(await ws.recv())
        for k in range(0, len(x), packet):
            await ws.send(encode_binary(0, k, x[k : k + packet]))
        await ws.send(json.dumps({"type": "stop"}))
        return started, [json.loads(m) async for m in ws]


def _rest(base: str, body: dict) -> dict:
    r = httpx.post(f"{base}/v1/pose/flex", json=body, timeout=120)
    assert r.status_code == 200, r.text
    return r.json()


def test_the_suit_model_answers_a_block_and_a_stream_alike(server: str, data_dir: Path) -> None:
    x = _suit_readings(data_dir)
    assert len(x) > 150
    block = _rest(server, {"samples": x.tolist()})  # four channels: the suit model is chosen by the row width
    assert block["model"]["name"] == SUIT and block["frames"] == len(x) - 99 and block["latency_samples"] == 1
    joints = list(block["angles_deg"])
    assert "LeftKnee" in joints and list(block["angles_deg"]["LeftKnee"]) == ["flexion", "abduction", "rotation"]
    started, messages = asyncio.run(
        _stream(server, {"type": "start", "model": SUIT, "channels": [f"{j}_flex" for j in FLEX_SENSOR_JOINTS]}, x, 3)
    )
    assert started["joints"] == joints and started["latency_samples"] == 1
    angles = [m for m in messages if m["type"] == "angles"]
    assert angles[0]["first_sample"] == block["first_sample"] == 98
    streamed = np.concatenate([np.asarray(m["angles_deg"]) for m in angles])
    rest = np.stack([[block["angles_deg"][j][c] for c in ("flexion", "abduction", "rotation")] for j in joints])
    np.testing.assert_allclose(streamed, rest.transpose(2, 0, 1), atol=2e-3)


def test_the_sleeve_model_takes_the_sleeves_own_100_hz(server: str, data_dir: Path) -> None:
    x, rate = read_capacitive_sleeve(data_dir, "CSBaseline", "Left")
    x = x[:3000].astype(np.float32)  # 30 s at 100 Hz
    block = _rest(server, {"model": SLEEVE, "samples": x.tolist(), "sample_rate_hz": rate})
    assert block["sample_rate_hz"] == 50.0 and list(block["angles_deg"]) == ["Knee"]
    start = {"type": "start", "model": SLEEVE, "channels": block_channels(server), "sample_rate_hz": rate}
    started, messages = asyncio.run(_stream(server, start, x, 10))
    assert started["decimation"] == 2
    streamed = np.concatenate([np.asarray(m["angles_deg"])[:, 0, 0] for m in messages if m["type"] == "angles"])
    rest = np.asarray(block["angles_deg"]["Knee"]["flexion"])
    # REST resamples (polyphase), the stream averages pairs: the same model on nearly the same readings
    n = min(len(rest), len(streamed))
    assert np.abs(rest[:n] - streamed[:n]).mean() < 1.0
    assert np.ptp(streamed) > 20.0  # a walking knee, not a constant
    # the same block as an OpenSim storage file, for OpenSim's tools
    r = httpx.post(
        f"{server}/v1/pose/flex",
        params={"format": "mot"},
        json={"model": SLEEVE, "samples": x.tolist(), "sample_rate_hz": rate},
        timeout=120,
    )
    assert r.status_code == 200 and r.headers["x-flex-model"].startswith(SLEEVE), r.text
    lines = r.text.splitlines()
    header = lines.index("endheader")
    assert "inDegrees=yes" in lines[:header] and lines[header + 1].split("\t") == ["time", "Knee_flexion"]
    table = np.array([[float(v) for v in line.split("\t")] for line in lines[header + 2 :]])
    np.testing.assert_allclose(table[:, 1], rest, atol=2e-3)
    assert table[0, 0] == pytest.approx(block["first_sample"] / 50.0)


def block_channels(base: str) -> list[str]:
    return httpx.get(f"{base}/v1/models").json()[SLEEVE]["channels"]


def test_stream_and_rest_mistakes_are_client_errors(server: str) -> None:
    r = httpx.post(f"{server}/v1/pose/flex", json={"model": SUIT, "samples": [[1.0, 2.0, 3.0, 9999.0]] * 120})
    assert r.status_code == 422 and "values must lie in [0, 4095]" in r.json()["detail"]

    async def bad() -> tuple[int, str]:
        async with websockets.connect(server.replace("http", "ws") + "/v1/stream/flex") as ws:
            await ws.send(json.dumps({"type": "start", "model": SUIT, "channels": ["a"]}))
            message = json.loads(await ws.recv())
            with pytest.raises(websockets.ConnectionClosed) as exc:
                await ws.recv()
            return exc.value.rcvd.code, message["detail"]

    code, detail = asyncio.run(bad())
    assert code == 1008 and "channels: flex_bilstm_cm takes ['LeftKnee_flex'" in detail


def test_a_failed_sleeve_read_out_is_refused_after_the_readings_before_it_are_answered(
    server: str, data_dir: Path
) -> None:
    """Sub01's right sleeve fails 39.7 s into the baseline trial (reading 3972 at 100 Hz: its Bot_Thigh channel
    jumps from about 1,160 to 1,750 and on to 1e8): REST refuses the block with where and what, a stream answers
    every reading before it and then closes."""
    x, rate = read_capacitive_sleeve(data_dir, "CSBaseline", "Right", until_failure=False)
    x = x[:4500].astype(np.float32)
    r = httpx.post(f"{server}/v1/pose/flex", json={"model": SLEEVE, "samples": x.tolist(), "sample_rate_hz": rate})
    assert r.status_code == 422, r.text
    detail = r.json()["detail"]
    assert "samples[3972]: channel Bot_Thigh read" in detail and "read-out has failed" in detail
    assert "send samples[:3972]" in detail
    before = _rest(server, {"model": SLEEVE, "samples": x[:3972].tolist(), "sample_rate_hz": rate})

    async def stream() -> tuple[list[dict], int]:
        async with websockets.connect(server.replace("http", "ws") + "/v1/stream/flex", max_size=None) as ws:
            channels = block_channels(server)
            await ws.send(json.dumps({"type": "start", "model": SLEEVE, "channels": channels, "sample_rate_hz": rate}))
            for k in range(0, len(x), 10):
                try:
                    await ws.send(encode_binary(0, k, x[k : k + 10]))
                except websockets.ConnectionClosed:
                    break
            messages = []
            with pytest.raises(websockets.ConnectionClosed) as exc:
                while True:
                    messages.append(json.loads(await ws.recv()))
            return messages, exc.value.rcvd.code

    messages, code = asyncio.run(stream())
    assert code == 1008
    error = messages[-1]
    assert error["type"] == "error" and "reading 3972 (packet seq 3970, row 2): channel Bot_Thigh" in error["detail"]
    answered = [m for m in messages if m["type"] == "angles"]
    last = answered[-1]["first_sample"] + answered[-1]["frames"] - 1
    (started,) = [m for m in messages if m["type"] == "started"]
    # every reading before the failure answered (pairs averaged to 50 Hz), but for the model's latency: a median
    # layer answers a reading once the next one has come
    assert last == 3972 // 2 - 1 - started["latency_samples"]
    assert len(before["angles_deg"]["Knee"]["flexion"]) == before["frames"] > 0
