"""``GET /dashboard``: the live view in the browser. The page and its scripts are static files of the service package
(``service/static/dashboard``, served under ``/static/dashboard``; three.js vendored from npm, MIT): the loaded models
with their manifests' evaluation figures and MLflow runs, and a bundled real recording that the browser streams
through ``/v1/stream`` (and ``/v1/stream/flex``) itself, at real time.

The page reads the models from ``/v1/models`` (with the key of its key field, when the service has one) and what only
the settings know from ``GET /dashboard/config.json``, which is not behind the key and says nothing about the
models.
"""

from __future__ import annotations

from fastapi import APIRouter, Request
from fastapi.responses import FileResponse

from service.api.landing import STATIC_DIR
from service.core.body import BODY_SEGMENTS, PARENT_INDEX

router = APIRouter()
PAGE = STATIC_DIR / "dashboard" / "index.html"


@router.get("/dashboard", include_in_schema=False)
async def dashboard() -> FileResponse:
    return FileResponse(PAGE, media_type="text/html; charset=utf-8")


@router.get("/dashboard/config.json", include_in_schema=False)
async def dashboard_config(request: Request) -> dict:
    """What the page needs from the settings: the MLflow UI, whether requests need a key, and the body's tree
    (for the stick figure of the pose messages' ``joint_positions_m``, in ``BODY_SEGMENTS`` order)."""
    settings = request.app.state.settings
    return {
        "ui_url": settings.ui_url.rstrip("/"),
        "key_required": bool(settings.api_key),
        "body": {"segments": list(BODY_SEGMENTS), "parents": list(PARENT_INDEX)},
    }
