"""``POST /v1/pose/flex``: joint angles from a block of flex-sensor or capacitive-sleeve readings (Chen et al. 2024),
every sample answered once the model's calibration window is full."""

from __future__ import annotations

from typing import Literal

import numpy as np
from fastapi import APIRouter, Depends, HTTPException, Query, Request, Response

from service.api.routes import _json, _Route, _settings, file_answer
from service.api.schemas import FlexRequest, FlexResponse, error_responses, file_responses
from service.core.opensim import format_opensim_storage
from service.inference.flex import MAX_FLEX_SAMPLES, FlexModel, block_rows
from service.inference.predict import InputError
from service.settings import Settings

router = APIRouter(route_class=_Route)


def flex_models(app) -> dict[str, FlexModel]:
    return app.state.flex_models


def choose_flex_model(models: dict[str, FlexModel], name: str | None, width: int | None) -> FlexModel:
    """The named model, else the one whose channel count is ``width`` (the rows' length), if just one is."""
    if not models:
        raise HTTPException(503, "no flex_pose model is loaded")
    listing = {n: m.manifest.channels for n, m in sorted(models.items())}
    if name is not None:
        if name not in models:
            raise HTTPException(422, f"model: no flex_pose model {name!r}; loaded (with their channels): {listing}")
        return models[name]
    fitting = [m for m in models.values() if len(m.manifest.channels) == width]
    if len(fitting) == 1:
        return fitting[0]
    why = "several" if fitting else "no"
    raise HTTPException(422, f"model: {why} loaded flex_pose model takes rows of {width} values; name one of {listing}")


def flex_answer(model: FlexModel, rows: np.ndarray, warnings: list[str]) -> FlexResponse:
    angles = model.run_block(rows)
    m = model.manifest
    per_joint = np.round(angles.astype(np.float64), 3)
    return FlexResponse(
        model={"name": m.name, "version": m.version},
        sample_rate_hz=m.sample_rate_hz,
        window_samples=model.window,
        latency_samples=model.latency,
        first_sample=model.window - 1 - model.latency,
        frames=len(angles),
        angles_deg={
            joint: {c: per_joint[:, j, k].tolist() for k, c in enumerate(m.joint_components)}
            for j, joint in enumerate(m.joints)
        },
        angle_convention=m.flex.angle_convention,
        warnings=warnings,
    )


def flex_storage(model: FlexModel, rows: np.ndarray) -> str:
    """The angles as an OpenSim storage file (``.mot``): time in seconds from the block's first sample (at the
    model's rate), one column per joint and component (``Knee_flexion``), in degrees."""
    angles = model.run_block(rows)
    m = model.manifest
    time_s = (model.window - 1 - model.latency + np.arange(len(angles))) / m.sample_rate_hz
    columns = {
        f"{joint}_{c}": angles[:, j, k].astype(np.float64)
        for j, joint in enumerate(m.joints)
        for k, c in enumerate(m.joint_components)
    }
    return format_opensim_storage(f"{m.name} {m.version}", time_s, columns, in_degrees=True)


@router.post(
    "/v1/pose/flex",
    response_model=FlexResponse,
    tags=["pose"],
    summary="Joint angles from a block of flex-sensor or capacitive-sleeve readings",
    description="The model (`GET /v1/models`, task `flex_pose`) declares its channels and their order, units and "
    "value range, rate, calibration window (`window_samples`), joints and angle convention. Every sample from the "
    "end of the first window on gets its angles (`latency_samples` behind the newest reading it saw). Other "
    "rates are resampled to the model's. Answers 503 while no flex_pose model is loaded. With `format=mot` the "
    "same angles come as an OpenSim storage file (time, then one column per joint and component, degrees); the "
    "model and warnings in the headers `X-Flex-Model` and `X-Flex-Warnings`.",
    responses=file_responses(
        "Flex", "flex_capacitive_knee 1.3.0\nversion=1\n...\nendheader\n...", "`mot` an OpenSim storage file"
    )
    | error_responses(
        400,
        401,
        413,
        415,
        422,
        503,
        details={
            422: {"a rule": "samples: a block must cover the calibration window of 100 samples at 20 Hz (5 s), ..."},
            503: {"no model": "no flex_pose model is loaded"},
        },
    ),
)
async def pose_from_flex(
    body: FlexRequest,
    request: Request,
    settings: Settings = Depends(_settings),
    format: Literal["json", "mot"] = Query(  # noqa: A002 (the query parameter's name)
        "json", description="`json` (default); `mot`: an OpenSim storage file of the angles"
    ),
) -> Response:
    width = len(body.samples[0])
    model = choose_flex_model(flex_models(request.app), body.model, width)
    if body.channels is not None and body.channels != model.manifest.channels:
        raise InputError(f"channels: {model.name} takes {model.manifest.channels} in this order, got {body.channels}")
    rows, warnings = block_rows(body.samples, body.sample_rate_hz, model, MAX_FLEX_SAMPLES)
    runner = request.app.state.runner
    if format == "mot":
        text = await runner.run_call(flex_storage, model, rows)
        return file_answer(text, f"{model.name}.mot", "Flex", model.name, model.manifest.version, warnings)
    return _json(await runner.run_call(flex_answer, model, rows, warnings))
