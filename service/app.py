"""FastAPI application factory: models are loaded in the lifespan, errors mapped to 4xx in one place."""

from __future__ import annotations

import logging
import time
from collections.abc import AsyncIterator
from contextlib import asynccontextmanager

from fastapi import FastAPI, Request
from fastapi.responses import JSONResponse

from service.api.metrics import ServiceMetrics
from service.api.routes import router
from service.api.stream import router as stream_router
from service.core.units import UnitError
from service.inference.batcher import MicroBatcher
from service.inference.predict import InputError
from service.inference.registry import LoadedModel, load_models
from service.settings import Settings, get_settings

log = logging.getLogger(__name__)


def _model_runner(models: dict[str, LoadedModel]):  # type: ignore[no-untyped-def]
    """Both I2S models on one batch: ``(B, 128, 6)`` → probabilities ``(B, 7)``, quaternions ``(B, 7, 4)``."""

    def run(imu):  # type: ignore[no-untyped-def]
        probs = models["i2s_assignment"].run(imu)
        quats = models["i2s_alignment"].run(imu) if "i2s_alignment" in models else None
        return probs, quats

    return run


def create_app(settings: Settings | None = None) -> FastAPI:
    settings = settings or get_settings()

    @asynccontextmanager
    async def lifespan(app: FastAPI) -> AsyncIterator[None]:
        app.state.models = load_models(settings.models_dir, settings.ort_threads)
        if not app.state.models:
            log.error("no valid model under %s", settings.models_dir.resolve())
        app.state.batcher = MicroBatcher(
            _model_runner(app.state.models),
            settings.batch_max_windows,
            settings.batch_max_wait_ms,
            app.state.metrics.observe_batch,
        )
        app.state.batcher.start()
        yield
        await app.state.batcher.stop()

    app = FastAPI(
        title="wearmocap",
        version="0.1.0",
        lifespan=lifespan,
        description="IMU-to-segment assignment and alignment (paper 000) served with onnxruntime.",
    )
    app.state.metrics = ServiceMetrics()
    app.state.settings = settings
    app.state.models = {}
    app.include_router(router)
    app.include_router(stream_router)

    @app.exception_handler(InputError)
    @app.exception_handler(UnitError)
    async def _bad_input(request: Request, exc: ValueError) -> JSONResponse:
        return JSONResponse({"detail": str(exc)}, status_code=422)

    @app.middleware("http")
    async def _guard(request: Request, call_next):  # type: ignore[no-untyped-def]
        start = time.perf_counter()
        length = request.headers.get("content-length")
        if length is not None and length.isdigit() and int(length) > settings.max_body_bytes:
            response = JSONResponse(
                {"detail": f"body of {length} bytes exceeds the limit of {settings.max_body_bytes} bytes"},
                status_code=413,
            )
        elif (
            settings.api_key
            and request.url.path.startswith("/v1/")
            and request.headers.get("x-api-key") != settings.api_key
        ):
            response = JSONResponse({"detail": "missing or wrong X-API-Key header"}, status_code=401)
        else:
            response = await call_next(request)
        metrics: ServiceMetrics = request.app.state.metrics
        metrics.requests.labels(request.url.path, str(response.status_code)).inc()
        metrics.latency.labels(request.url.path).observe(time.perf_counter() - start)
        return response

    return app
