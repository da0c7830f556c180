"""FastAPI application factory: models are loaded in the lifespan, errors mapped to 4xx in one place."""

from __future__ import annotations

import json
import logging
from collections.abc import AsyncIterator
from contextlib import asynccontextmanager

from fastapi import FastAPI, Request, Response
from fastapi.encoders import jsonable_encoder
from fastapi.exceptions import RequestValidationError

from service.api.flex_routes import router as flex_router
from service.api.flex_stream import router as flex_stream_router
from service.api.guard import Guard
from service.api.landing import router as landing_router
from service.api.metrics import ServiceMetrics
from service.api.pose_routes import router as pose_router
from service.api.routes import router
from service.api.stream import router as stream_router
from service.core.units import UnitError
from service.inference.batcher import MicroBatcher
from service.inference.flex import FlexModel
from service.inference.pose import PoseModel
from service.inference.predict import InputError
from service.inference.registry import load_models, load_registry_models
from service.inference.runner import ModelRunner
from service.settings import Settings, get_settings, parse_pins

log = logging.getLogger(__name__)


def create_app(settings: Settings | None = None) -> FastAPI:
    settings = settings or get_settings()

    @asynccontextmanager
    async def lifespan(app: FastAPI) -> AsyncIterator[None]:
        app.state.models = load_models(settings.models_dir, threads=1, pins=parse_pins(settings.model_versions))
        uris = [u.strip() for u in settings.registry_models.split(",") if u.strip()]
        for task, model in load_registry_models(
            settings.mlflow_tracking_uri, uris, settings.registry_cache_dir, threads=1
        ).items():
            if task in app.state.models:
                log.info("registry model %s replaces %s for %s", model.source, app.state.models[task].source, task)
            app.state.models[task] = model
        app.state.pose_models = {
            name: PoseModel(m) for name, m in app.state.models.items() if m.manifest.task == "imu_pose"
        }
        app.state.flex_models = {
            name: FlexModel(m) for name, m in app.state.models.items() if m.manifest.task == "flex_pose"
        }
        if not app.state.models:
            log.error("no valid model under %s", settings.models_dir.resolve())
        runner = app.state.runner = ModelRunner(
            app.state.models, settings.inference_threads, settings.inference_chunk_windows
        )
        app.state.batcher = MicroBatcher(
            runner.run_async,
            settings.batch_max_windows,
            settings.batch_max_wait_ms,
            app.state.metrics.observe_batch,
        )
        app.state.batcher.start()
        yield
        await app.state.batcher.stop()
        runner.close()

    app = FastAPI(
        title="wearmocap",
        version="0.1.0",
        lifespan=lifespan,
        description="Wearable motion capture served with onnxruntime: IMU-to-segment assignment and alignment "
        "(Zimmermann et al. 2018), whole-body pose from sparse IMUs (Zheng et al. 2021) and joint angles from "
        "flex sensors and capacitive sleeves (Chen et al. 2024).",
    )
    app.state.metrics = ServiceMetrics()
    app.state.settings = settings
    app.state.models = {}
    app.state.pose_models = {}
    app.state.flex_models = {}
    app.include_router(router)
    app.include_router(pose_router)
    app.include_router(flex_router)
    app.include_router(flex_stream_router)
    app.include_router(landing_router)
    app.include_router(stream_router)

    @app.exception_handler(InputError)
    @app.exception_handler(UnitError)
    async def _bad_input(request: Request, exc: ValueError) -> Response:
        return _ascii_json({"detail": str(exc)}, 422)

    @app.exception_handler(RequestValidationError)
    async def _invalid_request(request: Request, exc: RequestValidationError) -> Response:
        return _ascii_json({"detail": jsonable_encoder(exc.errors())}, 422)

    app.add_middleware(Guard, settings=settings, metrics=app.state.metrics)

    return app


def _ascii_json(content: object, status: int) -> Response:
    """Error answers echo client input; escaped to ASCII, a lone surrogate in it (valid JSON: "\\ud800") cannot
    make the answer unencodable, which FastAPI's default handler turns into a 500."""
    return Response(json.dumps(content, ensure_ascii=True), status_code=status, media_type="application/json")
