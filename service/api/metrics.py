"""Prometheus metrics, one registry per app (no global state)."""

from __future__ import annotations

from typing import TYPE_CHECKING

from prometheus_client import CollectorRegistry, Counter, Gauge, Histogram

if TYPE_CHECKING:
    from service.api.stream_admission import StreamAdmission
    from service.inference.batcher import MicroBatcher


class ServiceMetrics:
    def __init__(self) -> None:
        self.registry = CollectorRegistry()
        self.load_source: tuple[MicroBatcher, StreamAdmission] | None = None
        self.load_gauges: list[Gauge] = []
        self.requests = Counter("wearmocap_requests_total", "HTTP requests", ["path", "status"], registry=self.registry)
        self.latency = Histogram("wearmocap_request_seconds", "HTTP request latency", ["path"], registry=self.registry)
        self.batch = Histogram(
            "wearmocap_inference_batch_windows",
            "windows per inference call",
            buckets=(1, 2, 4, 8, 16, 32, 64, 128, 256, 512, 1024, 4096),
            registry=self.registry,
        )
        self.pose_batch = Histogram(
            "wearmocap_pose_batch_sessions",
            "live pose sessions per batched call of a streaming pose model",
            ["model"],
            buckets=(1, 2, 4, 8, 16, 32, 64, 128),
            registry=self.registry,
        )
        self.pose_batch_seconds = Histogram(
            "wearmocap_pose_batch_seconds",
            "worker time per batched call of a streaming pose model",
            ["model"],
            buckets=(0.0005, 0.001, 0.0025, 0.005, 0.01, 0.025, 0.05, 0.1),
            registry=self.registry,
        )
        self.inference = Histogram(
            "wearmocap_inference_seconds", "onnxruntime time per micro-batch", registry=self.registry
        )
        self.stream_result = Histogram(
            "wearmocap_stream_result_seconds",
            "stream packet received -> its window results queued for sending",
            buckets=(0.001, 0.0025, 0.005, 0.01, 0.025, 0.05, 0.1, 0.25, 0.5, 1.0, 2.5),
            registry=self.registry,
        )
        self.open_streams = Gauge("wearmocap_open_streams", "open WebSocket sessions", registry=self.registry)
        self.samples = Counter(
            "wearmocap_stream_samples_total", "sensor samples received on streams", registry=self.registry
        )
        self.gaps = Counter(
            "wearmocap_stream_sequence_problems_total", "sequence gaps and late packets", registry=self.registry
        )
        self.dropped = Counter(
            "wearmocap_stream_results_dropped_total", "results dropped for slow consumers", registry=self.registry
        )

        self.shed = Counter(
            "wearmocap_requests_shed_total",
            "requests answered 503 at once because the estimated wait passed their deadline",
            registry=self.registry,
        )
        self.streams_admitted = Counter(
            "wearmocap_streams_admitted_total", "WebSocket sessions admitted", registry=self.registry
        )
        self.streams_refused = Counter(
            "wearmocap_streams_refused_total",
            "WebSocket sessions refused (1013 at capacity, 1008 key or origin)",
            ["reason"],
            registry=self.registry,
        )
        self.streams_closed = Counter(
            "wearmocap_streams_closed_total",
            "WebSocket sessions closed, by close code",
            ["code"],
            registry=self.registry,
        )

    def watch_load(self, batcher: MicroBatcher, streams: StreamAdmission) -> None:
        """Gauges read at scrape time from the scheduler and the stream admission (registered once per app)."""
        self.load_source = (batcher, streams)
        if self.load_gauges:
            return
        self.load_gauges = [
            Gauge(name, text, registry=self.registry)
            for name, text in (
                ("wearmocap_capacity_windows_per_second", "measured inference capacity"),
                ("wearmocap_estimated_wait_seconds", "estimated wait of a request queued now"),
                ("wearmocap_stream_demand_windows_per_second", "admitted streams' demand"),
                ("wearmocap_event_loop_busy_share", "share of the last 2 s the event loop's thread was on the CPU"),
            )
        ]
        readers = (
            lambda b, s: b.capacity_windows_per_s or 0.0,
            lambda b, s: b.estimated_wait_s(),
            lambda b, s: s.total,
            lambda b, s: _nan_if_none(s.loop_busy_share()),  # NaN: too few timer ticks (a stalled loop)
        )
        for gauge, read in zip(self.load_gauges, readers, strict=True):
            gauge.set_function(lambda read=read: read(*self.load_source))

    def observe_batch(self, n: int, seconds: float) -> None:
        self.batch.observe(n)
        self.inference.observe(seconds)

    def observe_pose_batch(self, model: str, sessions: int, seconds: float) -> None:
        self.pose_batch.labels(model).observe(sessions)
        self.pose_batch_seconds.labels(model).observe(seconds)


def _nan_if_none(value: float | None) -> float:
    return float("nan") if value is None else value
