"""Prometheus metrics, one registry per app (no global state)."""

from __future__ import annotations

from prometheus_client import CollectorRegistry, Counter, Gauge, Histogram


class ServiceMetrics:
    def __init__(self) -> None:
        self.registry = CollectorRegistry()
        self.requests = Counter("wearmocap_requests_total", "HTTP requests", ["path", "status"], registry=self.registry)
        self.latency = Histogram("wearmocap_request_seconds", "HTTP request latency", ["path"], registry=self.registry)
        self.batch = Histogram(
            "wearmocap_inference_batch_windows",
            "windows per inference call",
            buckets=(1, 2, 4, 8, 16, 32, 64, 128, 256, 512, 1024, 4096),
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

    def observe_batch(self, n: int, seconds: float) -> None:
        self.batch.observe(n)
        self.inference.observe(seconds)
