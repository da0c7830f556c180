"""The pages a person opens: ``GET /``, a small landing page linking what a newcomer looks for (API docs, models,
metrics, the MLflow UI), and ``GET /docs``, the Swagger UI, served from the service package
(``service/static/swagger-ui``: swagger-ui-dist 5.35.0 from npm, Apache-2.0), so it works with no network."""

from __future__ import annotations

from html import escape
from pathlib import Path

from fastapi import APIRouter, Request
from fastapi.openapi.docs import get_swagger_ui_html
from fastapi.responses import HTMLResponse
from fastapi.staticfiles import StaticFiles

router = APIRouter()
STATIC_DIR = Path(__file__).resolve().parents[1] / "static"
SWAGGER_UI = "/static/swagger-ui"


def static_files() -> StaticFiles:
    """``/static``: the files the pages use, from the service package."""
    return StaticFiles(directory=STATIC_DIR)


@router.get("/docs", response_class=HTMLResponse, include_in_schema=False)
async def swagger_ui(request: Request) -> HTMLResponse:
    return get_swagger_ui_html(
        openapi_url=request.app.openapi_url,
        title=f"{request.app.title}: API",
        swagger_js_url=f"{SWAGGER_UI}/swagger-ui-bundle.js",
        swagger_css_url=f"{SWAGGER_UI}/swagger-ui.css",
        swagger_favicon_url=f"{SWAGGER_UI}/favicon-32x32.png",
    )


LINKS = (
    ("/dashboard", "live view: the models and a real recording streamed through the service, in the browser"),
    ("/docs", "API documentation (OpenAPI, try requests in the browser)"),
    ("/v1/models", "the loaded models and their manifests (JSON)"),
    ("/ready", "readiness"),
    ("/metrics", "Prometheus metrics"),
)


@router.get("/", response_class=HTMLResponse, include_in_schema=False)
async def landing(request: Request) -> HTMLResponse:
    settings = request.app.state.settings
    links = [(href, text) for href, text in LINKS] + [(settings.ui_url, "the MLflow UI: training runs and registry")]
    items = "".join(f'<li><a href="{escape(h)}">{escape(h)}</a>: {escape(t)}</li>' for h, t in links)
    if settings.api_key:
        models = "<p>The models are listed at /v1/models (send the X-API-Key header).</p>"
    else:
        rows = "".join(
            f"<tr><td>{escape(m.manifest.name)}</td><td>{escape(m.manifest.version)}</td>"
            f"<td>{escape(m.manifest.task)}</td></tr>"
            for _, m in sorted(request.app.state.models.items())
        )
        models = f"<table><tr><th>model</th><th>version</th><th>task</th></tr>{rows}</table>"
    body = (
        "<!doctype html><html><head><meta charset='utf-8'><title>wearmocap</title>"
        "<style>body{font-family:sans-serif;max-width:46em;margin:2em auto}td,th{padding:0 1em 0 0;text-align:left}"
        "</style></head><body><h1>wearmocap</h1><p>Learning-based wearable motion capture: IMU-to-segment "
        "assignment and alignment, whole-body pose from sparse IMUs, joint angles from flex sensors and capacitive "
        f"sleeves.</p><ul>{items}</ul><h2>Loaded models</h2>{models}</body></html>"
    )
    return HTMLResponse(body)
