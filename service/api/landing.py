"""``GET /``: a small landing page linking what a newcomer looks for (API docs, models, metrics, the MLflow UI)."""

from __future__ import annotations

from html import escape

from fastapi import APIRouter, Request
from fastapi.responses import HTMLResponse

router = APIRouter()

LINKS = (
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
