"""Thin routes: validate (schemas), convert (inference.predict), run models off the event loop."""

from __future__ import annotations

import asyncio
import json
import time
from collections.abc import Callable, Coroutine
from typing import Any

import numpy as np
import orjson
from fastapi import APIRouter, Depends, HTTPException, Query, Request, Response
from fastapi.responses import JSONResponse, PlainTextResponse
from fastapi.routing import APIRoute
from prometheus_client import CONTENT_TYPE_LATEST, generate_latest
from pydantic import BaseModel

from service.api.errors import ClientGone, excerpt
from service.api.schemas import (
    EXAMPLE_VERSIONS,
    MAX_WINDOWS_PER_REQUEST,
    WINDOW_ROWS_RULE,
    AccUnit,
    Alignment,
    AssignRequest,
    AssignResponse,
    GyrUnit,
    ImuWindow,
    Readiness,
    RefusedModel,
    SegmentName,
    SensorAssignment,
    WindowResult,
    WindowsRequest,
    WindowsResponse,
    error_responses,
    finite_or_none,
)
from service.core.assignment import (
    ConfidenceModel,
    assignment_confidence,
    gyro_norm,
    is_moving,
    session_assignment,
    session_swing_weight,
    turns_about_vertical,
    window_joint_assignment,
)
from service.core.segments import SEGMENTS, segment_index, segment_indices
from service.core.units import unit_warnings
from service.core.windowing import MODEL_RATE_HZ, WINDOW_SAMPLES
from service.inference.predict import (
    MAX_ABS_READING,
    MAX_RATE_HZ,
    MIN_RATE_HZ,
    MIN_WINDOW_ROWS,
    alignment_answer,
    mean_alignment,
    window_results,
    window_to_model_input,
    windows_to_model_input,
)
from service.inference.registry import LoadedModel
from service.settings import Settings


class _Request(Request):
    """Parses JSON bodies with orjson (several times faster than ``json`` on arrays of samples)."""

    async def json(self) -> Any:
        if not hasattr(self, "_json"):
            body = await self.body()
            try:
                self._json = orjson.loads(body)
            except orjson.JSONDecodeError:
                # orjson refuses NaN/Infinity literals; json reads them, so validation can say "must be finite",
                # and raises json.JSONDecodeError (FastAPI's 422) for anything that is not JSON at all.
                try:
                    self._json = json.loads(body)
                except UnicodeDecodeError as exc:
                    raise HTTPException(400, f"the body is not UTF-8 JSON: {exc.reason} at byte {exc.start}") from None
                except RecursionError:
                    raise HTTPException(400, "the body's JSON nests arrays or objects too deeply") from None
                except json.JSONDecodeError:
                    raise
                except ValueError:  # an integer of thousands of digits
                    raise HTTPException(
                        400, "the body's JSON has a number with too many digits for a reading"
                    ) from None
        return self._json


class _Route(APIRoute):
    def get_route_handler(self) -> Callable[[Request], Coroutine[Any, Any, Response]]:
        handler = super().get_route_handler()

        async def route(request: Request) -> Response:
            return await handler(_Request(request.scope, request.receive))

        return route


router = APIRouter(route_class=_Route)
TOO_MANY_WINDOWS = {413: {"too many windows": f"at most {MAX_WINDOWS_PER_REQUEST} windows per request, got 5000"}}
WINDOWS_ERRORS = error_responses(400, 401, 413, 415, 422, 503, details=TOO_MANY_WINDOWS)


def _models(request: Request) -> dict[str, LoadedModel]:
    return request.app.state.models


def _confidence(request: Request) -> ConfidenceModel | None:
    return request.app.state.confidence


async def _settings(request: Request) -> Settings:
    """The settings this app was created with (async: FastAPI would run a plain function in a thread)."""
    return request.app.state.settings


def _require(models: dict[str, LoadedModel], task: str) -> LoadedModel:
    if task not in models:
        raise HTTPException(503, f"no {task} model is loaded; loaded: {sorted(models) or 'none'}")
    return models[task]


def _check_count(n: int, settings: Settings, what: str = "windows") -> None:
    if n > settings.max_windows_per_request:
        raise HTTPException(413, f"at most {settings.max_windows_per_request} {what} per request, got {n}")


def _inputs(windows: list[ImuWindow], prefix: str) -> np.ndarray:
    return np.stack(
        [
            window_to_model_input(w.samples, w.sample_rate_hz, w.acc_unit, w.gyr_unit, f"{prefix}[{i}]")
            for i, w in enumerate(windows)
        ]
    )


async def infer_windows(request: Request, imu: np.ndarray) -> tuple[np.ndarray, np.ndarray | None, dict[str, str]]:
    """The I2S models' rows for ``imu``, scheduled with the request's deadline; the work is dropped if the client
    goes away while it waits (``ClientGone``). At most ``max_windows_per_request`` windows (else 413)."""
    _check_count(len(imu), request.app.state.settings)
    models = _models(request)
    _require(models, "i2s_assignment")
    batcher = request.app.state.batcher
    state = request.scope.get("state", {})
    batcher.release(state)  # the exact windows replace the Guard's estimate
    if "body_read" in state:
        batcher.observe_request_overhead(time.perf_counter() - state["body_read"])
    work = asyncio.ensure_future(batcher.infer(imu, start_by=state.get("start_by")))
    gone = asyncio.ensure_future(_disconnected(request))
    try:
        await asyncio.wait((work, gone), return_when=asyncio.FIRST_COMPLETED)
    finally:
        gone.cancel()
    if not work.done():
        work.cancel()
        raise ClientGone()
    probs, quats = work.result()
    versions = {m.manifest.name: m.manifest.version for m in models.values()}
    return probs, quats, versions


async def _disconnected(request: Request) -> None:
    """Returns when the client has gone (the body is read already: the next message is the disconnect)."""
    while (await request.receive())["type"] != "http.disconnect":
        pass


def _json(body: BaseModel) -> Response:
    """Serialise a response model once, with pydantic's serializer (FastAPI would validate it again first)."""
    return Response(body.model_dump_json(), media_type="application/json")


MAX_HEADER_WARNINGS = 8  # a proxy's response headers are limited (nginx: 4-8 KB by default)


def file_answer(text: str, filename: str, prefix: str, model: str, version: str, warnings: list[str]) -> Response:
    """A pose or angles as a file (BVH, OpenSim storage): the model and the warnings (the first
    ``MAX_HEADER_WARNINGS``, each cut to 200 characters, then how many more) in the headers ``X-{prefix}-Model``
    and ``X-{prefix}-Warnings`` (a JSON list; ASCII, as json.dumps escapes the rest)."""
    shown = [excerpt(w, 200) for w in warnings[:MAX_HEADER_WARNINGS]]
    if len(warnings) > MAX_HEADER_WARNINGS:
        shown.append(f"(and {len(warnings) - MAX_HEADER_WARNINGS} more: the JSON answer lists every one)")
    headers = {
        "Content-Disposition": f'attachment; filename="{filename}"',
        f"X-{prefix}-Model": f"{model} {version}",
        f"X-{prefix}-Warnings": json.dumps(shown),
    }
    return Response(text, media_type="text/plain; charset=utf-8", headers=headers)


def _window_results(
    imu: np.ndarray, probs: np.ndarray, quats: np.ndarray | None, segments: list[int | None]
) -> list[WindowResult]:
    turning = turns_about_vertical(imu)
    return [WindowResult(**r) for r in window_results(probs, quats, is_moving(imu), turning, segments)]


@router.post(
    "/v1/imu/windows",
    response_model=WindowsResponse,
    tags=["imu"],
    summary="Segment class and alignment per 128-sample IMU window",
    responses=WINDOWS_ERRORS,
)
async def classify_windows(body: WindowsRequest, request: Request, settings: Settings = Depends(_settings)) -> Response:
    _check_count(len(body.windows), settings)
    imu = _inputs(body.windows, "windows")
    probs, quats, versions = await infer_windows(request, imu)
    segments = [segment_index(w.segment) if w.segment else None for w in body.windows]
    units = sorted({(w.acc_unit, w.gyr_unit) for w in body.windows})
    warnings = [text for acc, gyr in units for text in unit_warnings(imu, acc, gyr)] if len(units) == 1 else []
    results = _window_results(imu, probs, quats, segments)
    return _json(WindowsResponse(results=results, model_versions=versions, warnings=warnings))


BINARY_BODY = (
    "little-endian float32, windows × samples_per_window × 6 values, row-major: for each window its samples "
    "in time order, each sample acc_x, acc_y, acc_z, gyr_x, gyr_y, gyr_z in the units given by the query. "
    "The length is a positive multiple of samples_per_window × 24 bytes (that many windows); every value is "
    f"finite and within ±{MAX_ABS_READING:g}"
)
# One 60 Hz window of zeros, 128 × 6 float32: the example body that goes with the query's defaults.
EXAMPLE_BINARY_BODY = "\0" * (WINDOW_SAMPLES * 6 * 4)


@router.post(
    "/v1/imu/windows/binary",
    response_model=WindowsResponse,
    tags=["imu"],
    summary="The same as /v1/imu/windows with the samples as a raw float32 body (no JSON parsing)",
    description="Body: " + BINARY_BODY + ". All windows of one request share rate, units and length; the "
    "number of windows is the body length / (samples_per_window × 24 bytes). Example: "
    "`curl --data-binary @windows.f32 -H 'content-type: application/octet-stream' "
    "'localhost:8000/v1/imu/windows/binary?sample_rate_hz=100&samples_per_window=214&acc_unit=g'`. "
    f"The example body is one {MODEL_RATE_HZ:g} Hz window of zeros: "
    f"{WINDOW_SAMPLES * 24} zero bytes.",
    responses=error_responses(401, 413, 422, 503, details=TOO_MANY_WINDOWS),
    openapi_extra={
        "requestBody": {
            "required": True,
            "content": {
                "application/octet-stream": {
                    "schema": {"type": "string", "format": "binary", "description": BINARY_BODY},
                    "example": EXAMPLE_BINARY_BODY,
                }
            },
        }
    },
)
async def classify_windows_binary(
    request: Request,
    sample_rate_hz: float = Query(MODEL_RATE_HZ, ge=MIN_RATE_HZ, le=MAX_RATE_HZ, examples=[MODEL_RATE_HZ]),
    acc_unit: AccUnit = "m/s^2",
    gyr_unit: GyrUnit = "rad/s",
    samples_per_window: int = Query(
        WINDOW_SAMPLES,
        ge=MIN_WINDOW_ROWS,
        le=65536,
        examples=[WINDOW_SAMPLES],
        description=f"rows per window. {WINDOW_ROWS_RULE}",
    ),
    segment: SegmentName | None = Query(None, description="known segment of every window: alignment given for it"),
    settings: Settings = Depends(_settings),
) -> Response:
    body = await request.body()
    per_window = samples_per_window * 6 * 4
    if not body or len(body) % per_window:
        raise HTTPException(
            422,
            f"body must be a whole number of windows of {samples_per_window} samples × 6 float32 "
            f"({per_window} bytes each), got {len(body)} bytes",
        )
    raw = np.frombuffer(body, dtype="<f4").reshape(-1, samples_per_window, 6)
    _check_count(len(raw), settings)
    imu = windows_to_model_input(raw.astype(np.float64), sample_rate_hz, acc_unit, gyr_unit, "window {i}")
    probs, quats, versions = await infer_windows(request, imu)
    segments = [segment_index(segment) if segment else None] * len(imu)
    results = _window_results(imu, probs, quats, segments)
    return _json(
        WindowsResponse(results=results, model_versions=versions, warnings=unit_warnings(imu, acc_unit, gyr_unit))
    )


@router.post(
    "/v1/imu/assign",
    response_model=AssignResponse,
    tags=["imu"],
    summary="Joint one-to-one assignment of simultaneously worn sensors to segments",
    responses=WINDOWS_ERRORS,
)
async def assign_sensors(body: AssignRequest, request: Request, settings: Settings = Depends(_settings)) -> Response:
    ids = [s.sensor_id for s in body.sensors]
    if len(set(ids)) != len(ids):
        raise HTTPException(422, f"sensor_id values must be unique, got {ids}")
    _check_count(sum(len(s.windows) for s in body.sensors), settings)
    per_sensor = [_inputs(s.windows, f"sensors[{k}].windows") for k, s in enumerate(body.sensors)]
    candidates = [segment_indices(s.candidate_segments) for s in body.sensors]
    answer = await assign_windows(
        request, ids, per_sensor, body.allow_shared, segment_indices(body.worn_segments), candidates
    )
    answer.warnings = [
        f"sensors[{k}] ({sensor.sensor_id}): {text}"
        for k, sensor in enumerate(body.sensors)
        if len({(w.acc_unit, w.gyr_unit) for w in sensor.windows}) == 1
        for text in unit_warnings(per_sensor[k], sensor.windows[0].acc_unit, sensor.windows[0].gyr_unit)
    ]
    return _json(answer)


async def assign_windows(
    request: Request,
    ids: list[str],
    per_sensor: list[np.ndarray],
    allow_shared: bool,
    worn: list[int] | None,
    candidates: list[list[int] | None],
) -> AssignResponse:
    """``/v1/imu/assign``'s answer (without warnings) for sensors worn together, each with its windows ``(n_k,
    128, 6)`` at 60 Hz in contract units, window k of each sensor the same moment."""
    probs, quats, versions = await infer_windows(request, np.concatenate(per_sensor))
    bounds = np.cumsum([0] + [len(x) for x in per_sensor])
    moving = [is_moving(x) for x in per_sensor]
    log_probs = [np.log(np.clip(probs[bounds[k] : bounds[k + 1]], 1e-12, 1.0)) for k in range(len(per_sensor))]
    norms = [gyro_norm(x) for x in per_sensor]  # how the sensors swing together
    weight = session_swing_weight(_confidence(request))
    joint, votes, n_moving = session_assignment(
        log_probs, moving, allow_shared, worn, candidates, norms, swing_weight=weight
    )
    at_moment = window_joint_assignment(log_probs, moving, allow_shared, worn, candidates, norms)
    calibrated = assignment_confidence(_confidence(request), joint, votes, n_moving)
    p_correct = calibrated.p_correct
    out = []
    for k, sensor_id in enumerate(ids):
        seg = int(joint.segment[k])
        alignment, spread = None, None
        if seg >= 0 and quats is not None:
            rows = quats[bounds[k] : bounds[k + 1], seg]
            # Still windows carry no information on rotation about gravity: average the moving ones if any.
            q, spread = mean_alignment(rows[moving[k]] if moving[k].any() else rows)
            alignment = Alignment(**alignment_answer(seg, q))
        out.append(
            SensorAssignment(
                sensor_id=sensor_id,
                segment=SEGMENTS[seg] if seg >= 0 else None,
                confidence=float(joint.confidence[k]),
                p_correct=None if p_correct is None else float(p_correct[k]),
                committed=None if calibrated.committed is None else bool(calibrated.committed[k]),
                margin=finite_or_none(joint.margin[k]),
                windows=len(per_sensor[k]),
                moving_windows=int(moving[k].sum()),
                moving_windows_turning_about_vertical=int((moving[k] & turns_about_vertical(per_sensor[k])).sum()),
                alignment=alignment,
                alignment_spread_deg=spread,
                window_segments=[SEGMENTS[g] if g >= 0 else None for g in at_moment[k].tolist()],
            )
        )
    return AssignResponse(
        sensors=out, p_all_correct=calibrated.p_all_correct, status=calibrated.status, model_versions=versions
    )


@router.get(
    "/v1/models",
    tags=["ops"],
    summary="Loaded models with their manifests",
    responses=error_responses(401)
    | {
        200: {
            "content": {
                "application/json": {
                    "example": {
                        "i2s_assignment": {
                            "name": "i2s_assignment",
                            "version": "1.9.0",
                            "classes": list(SEGMENTS),
                            "evaluations": [{"name": "loso_simulated", "metrics": {"accuracy": 0.997}}],
                            "source": "onnx_models/i2s_assignment/1.9.0",
                        }
                    }
                }
            }
        }
    },
)
async def list_models(request: Request) -> dict:
    return {task: {**m.manifest.model_dump(), "source": m.source} for task, m in _models(request).items()}


@router.get(
    "/health",
    tags=["ops"],
    summary="Liveness",
    responses={200: {"content": {"application/json": {"example": {"status": "alive"}}}}},
)
async def health() -> dict[str, str]:
    return {"status": "alive"}


@router.get(
    "/ready",
    tags=["ops"],
    summary="Readiness: at least the assignment model is loaded",
    response_model=Readiness,
    responses={
        200: {
            "content": {"application/json": {"example": {"ready": True, "status": "ok", "models": EXAMPLE_VERSIONS}}}
        },
        503: {
            "model": Readiness,
            "description": "not ready: no i2s_assignment model is loaded, or a pinned version cannot be served",
            "content": {"application/json": {"example": {"ready": False, "status": "unavailable", "models": {}}}},
        },
    },
)
async def ready(request: Request) -> JSONResponse:
    models = _models(request)
    report = getattr(request.app.state, "load_report", None)
    failed_pins = report.failed_pins if report else {}
    ok = "i2s_assignment" in models and not failed_pins
    status = "unavailable" if not ok else "degraded" if report and report.newer_refused() else "ok"
    body = Readiness(
        ready=ok,
        status=status,
        models={t: m.manifest.version for t, m in models.items()},
        refused=[RefusedModel(**vars(r)) for r in (report.refused if report else [])],
        failed_pins=failed_pins,
    )
    return JSONResponse(body.model_dump(), status_code=200 if ok else 503)


@router.get(
    "/metrics",
    tags=["ops"],
    summary="Prometheus metrics",
    response_class=PlainTextResponse,
    responses=error_responses(401)
    | {
        200: {
            "content": {
                "text/plain": {"example": 'wearmocap_requests_total{path="/v1/imu/windows",status="200"} 42.0\n'}
            }
        }
    },
)
async def metrics(request: Request) -> Response:
    return Response(generate_latest(request.app.state.metrics.registry), media_type=CONTENT_TYPE_LATEST)
