"""Every error answer in one shape and of bounded size: ``{"detail": str}``, and for a 422 of the request schema
also ``errors`` (at most ``MAX_FIELD_ERRORS``, each quoting at most ``MAX_EXCERPT_CHARS`` of what arrived) and
``errors_total``. A 30 MB invalid body gets a short answer, never its own echo."""

from __future__ import annotations

import json
from typing import Any

from fastapi import FastAPI, Request, Response
from fastapi.exceptions import RequestValidationError
from starlette.exceptions import HTTPException as StarletteHTTPException

from service.core.units import UnitError
from service.inference.batcher import Overloaded
from service.inference.predict import InputError

MAX_FIELD_ERRORS = 20
MAX_EXCERPT_CHARS = 200
MAX_DETAIL_CHARS = 1000


class ClientGone(Exception):
    """The client closed the connection before its answer was ready; its queued work was dropped."""


def excerpt(text: str, limit: int = MAX_EXCERPT_CHARS) -> str:
    """``text`` cut to ``limit`` characters, saying how long it was."""
    return text if len(text) <= limit else f"{text[:limit]}… ({len(text)} characters)"


def _input_excerpt(value: Any) -> str | None:
    if value is None:
        return None
    try:
        text = json.dumps(value, ensure_ascii=True, default=str)
    except (TypeError, ValueError):
        text = repr(value)
    return excerpt(text)


def _with_reason(err: dict) -> str:
    """pydantic's message, with the parser's reason where it keeps one apart (a body that is not JSON)."""
    msg, reason = str(err.get("msg", "")), (err.get("ctx") or {}).get("error")
    return f"{msg} ({reason})" if err.get("type") == "json_invalid" and reason else msg


def field_errors(errors: list[dict]) -> dict[str, Any]:
    """pydantic's errors → the bounded body of a 422."""
    shown = [
        {
            "loc": [p if isinstance(p, int) else str(p) for p in err.get("loc", ())],
            "msg": excerpt(_with_reason(err), MAX_EXCERPT_CHARS),
            "type": str(err.get("type", "")),
            "input": _input_excerpt(err.get("input")),
        }
        for err in errors[:MAX_FIELD_ERRORS]
    ]
    first = shown[0] if shown else {"loc": [], "msg": "invalid request"}
    where = ".".join(str(p) for p in first["loc"])
    more = f" (and {len(errors) - 1} more)" if len(errors) > 1 else ""
    return {
        "detail": f"{where}: {first['msg']}{more}" if where else first["msg"],
        "errors": shown,
        "errors_total": len(errors),
    }


def _not_json(content_type: str) -> str | None:
    """What a Content-Type header that is not JSON says (FastAPI reads only ``application/json`` and
    ``application/*+json`` bodies as JSON, and no body without the header); None for JSON."""
    media = content_type.split(";", 1)[0].strip().lower()
    if media == "application/json" or (media.startswith("application/") and media.endswith("+json")):
        return None
    return excerpt(media, 80) if media else "no Content-Type"


def error_response(status: int, detail: str, headers: dict[str, str] | None = None, **extra: Any) -> Response:
    """The one error body; escaped to ASCII, so a lone surrogate echoed from the client cannot make it
    unencodable."""
    body = {"detail": excerpt(detail, MAX_DETAIL_CHARS), **extra}
    return Response(json.dumps(body, ensure_ascii=True), status, headers, media_type="application/json")


def install_error_handlers(app: FastAPI) -> None:
    @app.exception_handler(InputError)
    @app.exception_handler(UnitError)
    async def _bad_input(request: Request, exc: ValueError) -> Response:
        return error_response(422, str(exc))

    @app.exception_handler(RequestValidationError)
    async def _invalid_request(request: Request, exc: RequestValidationError) -> Response:
        errors = list(exc.errors())
        if (not_json := _not_json(request.headers.get("content-type", ""))) and any(
            tuple(e.get("loc", ())) == ("body",) and e.get("type") != "missing" for e in errors
        ):  # FastAPI reads a body as JSON only under a JSON Content-Type: else it fails as "not a valid dictionary"
            return error_response(415, f"this route takes a JSON body (Content-Type: application/json); got {not_json}")
        body = field_errors(errors)
        return error_response(422, body.pop("detail"), **body)

    @app.exception_handler(StarletteHTTPException)
    async def _http(request: Request, exc: StarletteHTTPException) -> Response:
        return error_response(exc.status_code, str(exc.detail), dict(exc.headers or {}))

    @app.exception_handler(ClientGone)
    async def _gone(request: Request, exc: ClientGone) -> Response:
        # Nobody reads it; 499 ("client closed request", as nginx logs it) keeps /metrics honest.
        return error_response(499, "the client closed the connection; its work was dropped")

    @app.exception_handler(Overloaded)
    async def _overloaded(request: Request, exc: Overloaded) -> Response:
        request.app.state.metrics.shed.inc()
        return error_response(503, str(exc), {"Retry-After": str(exc.retry_after_s)})
