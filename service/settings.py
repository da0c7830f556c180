"""Service settings from the environment (prefix ``WEARMOCAP_``), validated at start-up."""

from __future__ import annotations

from functools import lru_cache
from pathlib import Path

from pydantic import Field
from pydantic_settings import BaseSettings, SettingsConfigDict


class Settings(BaseSettings):
    model_config = SettingsConfigDict(env_prefix="WEARMOCAP_")

    models_dir: Path = Field(Path("onnx_models"), description="root of <name>/<version>/model.onnx + manifest.json")
    inference_threads: int = Field(
        2, ge=1, description="parallel onnxruntime calls (each single-threaded); about the number of cores"
    )
    inference_chunk_windows: int = Field(8, ge=1, description="windows per onnxruntime call within a batch")
    max_windows_per_request: int = Field(4096, ge=1)
    max_body_bytes: int = Field(32 * 1024 * 1024, ge=1024)
    batch_max_wait_ms: float = Field(
        0.0,
        ge=0,
        description="extra wait for company for a part-filled chunk of REST windows; 0: windows queued while "
        "chunks run fill the next ones",
    )
    request_deadline_s: float = Field(
        2.0,
        gt=0,
        description="longest a REST request may wait before its work starts; when the estimated wait of the "
        "inference queue passes it, the answer is 503 with Retry-After at once",
    )
    capacity_windows_per_s: float = Field(
        0.0,
        ge=0,
        description="windows/s the inference workers hold, kept as set; 0: measured by a start-up probe (then "
        "refined by the chunks run)",
    )
    stream_capacity_fraction: float = Field(
        0.5,
        gt=0,
        le=1,
        description="share of the capacity that live streams may take; a new stream beyond it is refused with 1013",
    )
    stream_pose_busy_limit: float = Field(
        0.8,
        gt=0,
        le=1,
        description="a new live pose session is refused with 1013 when the pose worker's busy share over the last "
        "2 s, projected with the sessions opened since and the new one, passes this (its batches grow with the "
        "sessions, so a busy worker still answers within a few batch times)",
    )
    stream_latency_target_ms: float = Field(
        100.0,
        gt=0,
        description="a new stream is refused with 1013 while the admitted streams' packet-to-answer p99 over the last "
        "10 s passes this",
    )
    stream_slow_consumer_s: float = Field(
        5.0,
        gt=0,
        description="a WebSocket client that has not taken a message for this long while messages wait for it, or "
        "whose results were dropped for this long, is closed with 1008 and a reason",
    )
    stream_batch_wait_ms: float = Field(
        10.0,
        ge=0,
        description="how long a stream window may wait for company in a micro-batch (larger batches "
        "cost less CPU per window; a sensor's next window is 267 ms away at 60 Hz)",
    )
    stream_queue_limit: int = Field(1024, ge=8, description="outgoing messages queued per WebSocket")
    stream_max_pending_windows: int = Field(
        256,
        ge=1,
        description="windows of one WebSocket session waiting for inference; beyond it the server stops "
        "reading that socket until inference catches up (TCP back-pressure: nothing is dropped)",
    )
    stream_max_samples_per_packet: int = Field(4096, ge=1)
    stream_alignment_windows: int = Field(
        450,
        ge=1,
        description="a streamed sensor's alignment in the assignment message is the robust mean over its last this "
        "many moving windows (450: about two minutes at 60 Hz, hop 16)",
    )
    stream_assignment_interval_s: float = Field(
        0.5,
        ge=0,
        description="a stream's running assignment message goes out after its first results, then once the session "
        "has answered as many windows as its sensors make in this many seconds of stream time (0.5: two per sensor), "
        "and at the end; after every group of results while a pose calibrated from the assignment waits for it, and "
        "with 0",
    )
    ws_ping_interval_s: float = Field(10.0, gt=0, description="WebSocket ping interval (python -m service)")
    ws_ping_timeout_s: float = Field(
        10.0,
        gt=0,
        description="a WebSocket client that does not answer a ping within this is closed with 1008 and a reason (it "
        "has stopped reading)",
    )
    model_versions: str = Field(
        "", description="comma-separated <name>=<version> pins, e.g. i2s_alignment=1.0.0; default: newest version"
    )
    mlflow_tracking_uri: str | None = Field(None, description="MLflow tracking server (http/https) for registry models")
    registry_models: str = Field(
        "",
        description="comma-separated models:/<name>@<alias> or models:/<name>/<version>; each replaces the "
        "local model of its task",
    )
    registry_cache_dir: Path = Field(Path(".cache/registry_models"), description="where registry models are stored")
    api_key: str | None = Field(None, description="if set, requests must send it in the X-API-Key header")
    metrics_require_key: bool = Field(False, description="/metrics also asks for the API key (when one is set)")
    allowed_origins: str = Field(
        "",
        description="comma-separated browser origins (https://app.example.org) allowed to call the API (CORS) and "
        "to open WebSockets; empty: no CORS headers, and WebSockets from any origin",
    )
    strict_models: bool = Field(
        False,
        description="refuse to start when any model file under models_dir is refused (bad sha256, unreadable, "
        "no manifest) instead of serving the others with /ready 'degraded'",
    )
    ui_url: str = Field("http://127.0.0.1:5000", description="the MLflow UI that the landing page (GET /) links")


def parse_pins(text: str) -> dict[str, str]:
    """``"a=1.0.0, b=2"`` → ``{"a": "1.0.0", "b": "2"}``."""
    pins = {}
    for item in filter(None, (part.strip() for part in text.split(","))):
        name, sep, version = item.partition("=")
        if not sep or not name.strip() or not version.strip():
            raise ValueError(f"model_versions entries look like <name>=<version>, got {item!r}")
        pins[name.strip()] = version.strip()
    return pins


@lru_cache
def get_settings() -> Settings:
    return Settings()
