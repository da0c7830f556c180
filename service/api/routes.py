"""Thin routes: validate (schemas), convert (inference.predict), run models off the event loop."""

from __future__ import annotations

import numpy as np
from fastapi import APIRouter, Depends, HTTPException, Request, Response
from fastapi.responses import JSONResponse
from prometheus_client import CONTENT_TYPE_LATEST, generate_latest

from service.api.schemas import (
    Alignment,
    AssignRequest,
    AssignResponse,
    ImuWindow,
    SensorAssignment,
    WindowResult,
    WindowsRequest,
    WindowsResponse,
)
from service.core.assignment import is_moving, joint_assignment
from service.core.segments import SEGMENTS, segment_index
from service.inference.predict import alignment_payload, mean_alignment, window_result, window_to_model_input
from service.inference.registry import LoadedModel
from service.settings import Settings, get_settings

router = APIRouter()


def _models(request: Request) -> dict[str, LoadedModel]:
    return request.app.state.models


def _require(models: dict[str, LoadedModel], task: str) -> LoadedModel:
    if task not in models:
        raise HTTPException(503, f"no {task} model is loaded; loaded: {sorted(models) or 'none'}")
    return models[task]


def _check_count(n: int, settings: Settings) -> None:
    if n > settings.max_windows_per_request:
        raise HTTPException(413, f"at most {settings.max_windows_per_request} windows per request, got {n}")


def _inputs(windows: list[ImuWindow], prefix: str) -> np.ndarray:
    return np.stack(
        [
            window_to_model_input(w.samples, w.sample_rate_hz, w.acc_unit, w.gyr_unit, f"{prefix}[{i}]")
            for i, w in enumerate(windows)
        ]
    )


async def _infer(request: Request, imu: np.ndarray) -> tuple[np.ndarray, np.ndarray | None, dict[str, str]]:
    models = _models(request)
    _require(models, "i2s_assignment")
    probs, quats = await request.app.state.batcher.infer(imu)
    versions = {m.manifest.name: m.manifest.version for m in models.values()}
    return probs, quats, versions


@router.post(
    "/v1/imu/windows",
    response_model=WindowsResponse,
    tags=["imu"],
    summary="Segment class and alignment per 128-sample IMU window",
)
async def classify_windows(
    body: WindowsRequest, request: Request, settings: Settings = Depends(get_settings)
) -> WindowsResponse:
    _check_count(len(body.windows), settings)
    imu = _inputs(body.windows, "windows")
    probs, quats, versions = await _infer(request, imu)
    moving = is_moving(imu)
    results = [
        WindowResult(
            **window_result(
                probs[i],
                None if quats is None else quats[i],
                moving[i],
                segment_index(w.segment) if w.segment else None,
            )
        )
        for i, w in enumerate(body.windows)
    ]
    return WindowsResponse(results=results, model_versions=versions)


@router.post(
    "/v1/imu/assign",
    response_model=AssignResponse,
    tags=["imu"],
    summary="Joint one-to-one assignment of simultaneously worn sensors to segments",
)
async def assign_sensors(
    body: AssignRequest, request: Request, settings: Settings = Depends(get_settings)
) -> AssignResponse:
    ids = [s.sensor_id for s in body.sensors]
    if len(set(ids)) != len(ids):
        raise HTTPException(422, f"sensor_id values must be unique, got {ids}")
    _check_count(sum(len(s.windows) for s in body.sensors), settings)
    per_sensor = [_inputs(s.windows, f"sensors[{k}].windows") for k, s in enumerate(body.sensors)]
    probs, quats, versions = await _infer(request, np.concatenate(per_sensor))
    bounds = np.cumsum([0] + [len(x) for x in per_sensor])
    log_probs, moving = [], []
    for k, x in enumerate(per_sensor):
        mask = is_moving(x)
        p = probs[bounds[k] : bounds[k + 1]]
        moving.append(mask)
        log_probs.append(np.log(np.clip(p[mask] if mask.any() else p, 1e-12, 1.0)))
    joint = joint_assignment(log_probs, allow_shared=body.allow_shared)
    out = []
    for k, sensor in enumerate(body.sensors):
        seg = int(joint.segment[k])
        alignment = None
        if seg >= 0 and quats is not None:
            q = mean_alignment(quats[bounds[k] : bounds[k + 1], seg])
            a_q, a_R = alignment_payload(q[None].repeat(len(SEGMENTS), 0), seg)
            alignment = Alignment(segment=SEGMENTS[seg], q_segment_imu=a_q, R_segment_imu=a_R)
        out.append(
            SensorAssignment(
                sensor_id=sensor.sensor_id,
                segment=SEGMENTS[seg] if seg >= 0 else None,
                confidence=float(joint.confidence[k]),
                margin=float(joint.margin[k]),
                windows=len(per_sensor[k]),
                moving_windows=int(moving[k].sum()),
                alignment=alignment,
            )
        )
    return AssignResponse(sensors=out, model_versions=versions)


@router.get("/v1/models", tags=["ops"], summary="Loaded models with their manifests")
async def list_models(request: Request) -> dict:
    return {task: m.manifest.model_dump() for task, m in _models(request).items()}


@router.get("/health", tags=["ops"], summary="Liveness")
async def health() -> dict[str, str]:
    return {"status": "alive"}


@router.get("/ready", tags=["ops"], summary="Readiness: at least the assignment model is loaded")
async def ready(request: Request) -> JSONResponse:
    models = _models(request)
    ok = "i2s_assignment" in models
    body = {"ready": ok, "models": {t: m.manifest.version for t, m in models.items()}}
    return JSONResponse(body, status_code=200 if ok else 503)


@router.get("/metrics", tags=["ops"], summary="Prometheus metrics")
async def metrics(request: Request) -> Response:
    return Response(generate_latest(request.app.state.metrics.registry), media_type=CONTENT_TYPE_LATEST)
