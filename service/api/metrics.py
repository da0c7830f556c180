"""Prometheus metrics, one registry per app (no global state)."""

from __future__ import annotations

from prometheus_client import CollectorRegistry, Counter, Histogram


class ServiceMetrics:
    def __init__(self) -> None:
        self.registry = CollectorRegistry()
        self.requests = Counter("wearmocap_requests_total", "HTTP requests", ["path", "status"],
                                registry=self.registry)
        self.latency = Histogram("wearmocap_request_seconds", "HTTP request latency", ["path"],
                                 registry=self.registry)
        self.batch = Histogram("wearmocap_inference_batch_windows", "windows per inference call",
                               buckets=(1, 2, 4, 8, 16, 32, 64, 128, 256, 512, 1024, 4096), registry=self.registry)

    def observe_batch(self, n: int) -> None:
        self.batch.observe(n)
