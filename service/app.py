"""FastAPI application factory: models are loaded in the lifespan, errors mapped to 4xx in one place."""

from __future__ import annotations

import asyncio
import logging
from collections.abc import AsyncIterator
from contextlib import asynccontextmanager

import numpy as np
from fastapi import FastAPI
from fastapi.middleware.cors import CORSMiddleware

from service.api.dashboard import router as dashboard_router
from service.api.errors import install_error_handlers
from service.api.flex_routes import router as flex_router
from service.api.flex_stream import router as flex_stream_router
from service.api.guard import Guard, allowed_origins
from service.api.landing import router as landing_router
from service.api.landing import static_files
from service.api.metrics import ServiceMetrics
from service.api.pose_routes import router as pose_router
from service.api.request_cost import seed_request_cost
from service.api.routes import router
from service.api.stream import router as stream_router
from service.api.stream_admission import StreamAdmission, flex_batch_observer
from service.core.assignment import ConfidenceModel
from service.inference.batcher import MicroBatcher
from service.inference.flex import FlexModel, probe_sessions, process_live_flex
from service.inference.pose import PoseModel, cost_key
from service.inference.pose_batcher import LivePoseBatcher
from service.inference.registry import load_model_report, load_registry_models
from service.inference.runner import ModelRunner
from service.inference.session_batcher import SessionBatcher
from service.inference.velocity import VelocityModel, velocity_model_for
from service.settings import Settings, get_settings, parse_pins

log = logging.getLogger(__name__)


def create_app(settings: Settings | None = None) -> FastAPI:
    settings = settings or get_settings()

    @asynccontextmanager
    async def lifespan(app: FastAPI) -> AsyncIterator[None]:
        report = app.state.load_report = load_model_report(
            settings.models_dir, threads=1, pins=parse_pins(settings.model_versions)
        )
        uris = [u.strip() for u in settings.registry_models.split(",") if u.strip()]
        for task, model in load_registry_models(
            settings.mlflow_tracking_uri, uris, settings.registry_cache_dir, threads=1, report=report
        ).items():
            if task in report.models:
                log.info("registry model %s replaces %s for %s", model.source, report.models[task].source, task)
            report.models[task] = model
        if settings.strict_models and (report.refused or report.failed_pins):
            problems = [f"{r.path}: {r.reason}" for r in report.refused] + list(report.failed_pins.values())
            raise RuntimeError(f"WEARMOCAP_STRICT_MODELS: refusing to start; {'; '.join(problems)}")
        app.state.models = report.models
        app.state.pose_models = {
            name: PoseModel(m) for name, m in app.state.models.items() if m.manifest.task == "imu_pose"
        }
        app.state.velocity_models = {
            name: VelocityModel(m) for name, m in app.state.models.items() if m.manifest.task == "imu_pose_velocity"
        }
        app.state.flex_models = {
            name: FlexModel(m) for name, m in app.state.models.items() if m.manifest.task == "flex_pose"
        }
        assignment = app.state.models.get("i2s_assignment")
        app.state.confidence = ConfidenceModel.from_spec(assignment.manifest.confidence if assignment else None)
        if not app.state.models:
            log.error("no valid model under %s", settings.models_dir.resolve())
        runner = app.state.runner = ModelRunner(
            app.state.models, settings.inference_threads, settings.inference_chunk_windows
        )
        batcher = app.state.batcher = MicroBatcher(
            runner.run_chunk_async,
            settings.inference_threads,
            settings.inference_chunk_windows,
            settings.batch_max_wait_ms,
            app.state.metrics.observe_batch,
        )
        batcher.start()

        pose_batcher = app.state.pose_batcher = LivePoseBatcher(runner, 1, app.state.metrics.observe_pose_batch)
        flex_batcher = app.state.flex_batcher = SessionBatcher(runner, process_live_flex, 1)
        for name, model in app.state.flex_models.items():
            per_batch, per_frame = await flex_batcher.probe(name, probe_sessions(model, 32, 2), 32, 2)
            app.state.streams.set_frame_cost(name, per_frame)
            log.info("flex probe %s: %.2f ms per batch + %.3f ms per frame", name, 1e3 * per_batch, 1e3 * per_frame)
        flex_batcher.on_batch = flex_batch_observer(
            app.state.streams, lambda name: flex_batcher.per_batch_s.get(name, 0)
        )
        for model in app.state.pose_models.values():
            if not model.spec.streaming:
                continue
            velocity = velocity_model_for(app.state.velocity_models, model.spec)
            for beside in [None] if velocity is None else [None, velocity]:  # and with translation learned
                per_batch, per_frame = await pose_batcher.probe(model, 32 if model.batchable else 2, velocity=beside)
                key = cost_key(model, beside)
                app.state.streams.set_frame_cost(key, per_frame)
                log.info("pose probe %s: %.2f ms per batch + %.3f ms per frame", key, 1e3 * per_batch, 1e3 * per_frame)
        if settings.capacity_windows_per_s:
            batcher.set_capacity(settings.capacity_windows_per_s)
        elif "i2s_assignment" in app.state.models:
            capacity = await batcher.probe(lambda n: np.zeros((n, 128, 6), np.float32))
            log.info("capacity probe: %.0f windows/s on %d workers", capacity, settings.inference_threads)
        if "i2s_assignment" in app.state.models:
            await seed_request_cost(app, settings.api_key)
        app.state.metrics.watch_load(batcher, app.state.streams)
        loop_watch = asyncio.create_task(app.state.streams.watch_loop())
        yield
        loop_watch.cancel()
        await batcher.stop()
        runner.close()

    app = FastAPI(
        docs_url=None,  # served by service.api.landing from the package's own Swagger UI files, not a CDN
        redoc_url=None,
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
    app.state.velocity_models = {}
    app.state.flex_models = {}
    app.state.confidence = None
    app.state.streams = StreamAdmission(
        settings.stream_capacity_fraction, settings.stream_latency_target_ms, settings.stream_pose_busy_limit
    )
    app.include_router(router)
    app.include_router(pose_router)
    app.include_router(flex_router)
    app.include_router(flex_stream_router)
    app.include_router(landing_router)
    app.include_router(dashboard_router)
    app.mount("/static", static_files(), name="static")
    app.include_router(stream_router)

    install_error_handlers(app)
    app.add_middleware(Guard, settings=settings, metrics=app.state.metrics, state=app.state)
    if allowed_origins(settings):  # outermost: a browser's preflight carries no key
        app.add_middleware(
            CORSMiddleware,
            allow_origins=allowed_origins(settings),
            allow_methods=["GET", "POST"],
            allow_headers=["*"],
            max_age=600,
        )

    return app
