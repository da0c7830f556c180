"""Schema fuzzing: the OpenAPI document and the service say the same thing.

Schemathesis' Hypothesis strategies (its pytest plugin does not support this pytest) send every operation its
documented examples, schema-valid (positive) and schema-violating (negative) requests, against a real uvicorn
server with tiny and shipped ONNX models. Every answer passes schemathesis' checks: a status code the operation
declares, a body and headers that conform to the declared schema, a declared content type, and a negative request
refused. No answer is a 5xx, but a 503 where declared. Positive requests are accepted (2xx) unless they break a rule
the document states in words, in a field's description (``violates_documented_rule``): those are filtered out with
``assume`` and counted.
"""

from __future__ import annotations

import math
import shutil
import time
from collections import Counter
from fractions import Fraction
from pathlib import Path

import httpx
import numpy as np
import schemathesis
from hypothesis import HealthCheck, assume, given, settings
from schemathesis.specs.openapi.checks import (
    content_type_conformance,
    negative_data_rejection,
    response_headers_conformance,
    response_schema_conformance,
    status_code_conformance,
)

from benchmarks.servers import start_service, stop
from service.api.schemas import MAX_WINDOWS_PER_REQUEST
from service.core.windowing import MODEL_RATE_HZ, WINDOW_SAMPLES
from tests.service.conftest import write_tiny_model

MODELS = Path(__file__).resolve().parents[2] / "onnx_models"
CASES_PER_OPERATION = 20  # per operation and mode: about 210 requests in all, 25-50 s on two busy cores
CHECKS = [
    status_code_conformance,
    response_schema_conformance,
    response_headers_conformance,
    content_type_conformance,
    negative_data_rejection,
]
# A schema-violating request is refused with one of the refusals the document declares (a 503 is no verdict on
# the data: the service sheds load before it reads a body).
CONFIG = schemathesis.Config.from_dict(
    {"checks": {"negative_data_rejection": {"expected-statuses": ["400", "401", "413", "422", "503"]}}}
)
# Positive requests must be accepted on these operations. On the others a documented rule refuses nearly every
# generated body, so there only the documented examples are checked for acceptance: /v1/pose/imu takes exactly a
# loaded model's sensors with unit quaternions, /v1/pose/flex rows as wide as a loaded model's channels, in its
# value range and covering its window, /v1/imu/windows/binary a body of whole windows as the query describes them.
ACCEPTANCE_CHECKED = {
    "POST /v1/imu/windows",
    "POST /v1/imu/assign",
    "GET /v1/models",
    "GET /health",
    "GET /ready",
    "GET /metrics",
}


def test_the_service_answers_as_its_openapi_document_says(tmp_path: Path) -> None:
    root = tmp_path / "onnx_models"
    write_tiny_model(root, "i2s_assignment")
    write_tiny_model(root, "i2s_alignment")
    # The shipped models the examples name: with one model loaded per placement and channel count, the routes'
    # "the model that fits" is never ambiguous.
    for name in ("pose_lower3", "flex_bilstm_cm"):
        shutil.copytree(MODELS / name, root / name)
    server, base = start_service(root, max_body_bytes="1000000")
    tally: Counter[str] = Counter()
    start = time.perf_counter()
    try:
        schema = schemathesis.openapi.from_url(f"{base}/openapi.json", config=CONFIG)
        labels = []
        for result in schema.get_all_operations():
            operation = result.ok()
            labels.append(f"{operation.method.upper()} {operation.path}")
            _examples(operation, tally)
            post = operation.method.lower() == "post"
            for mode in list(schemathesis.GenerationMode) if post else [schemathesis.GenerationMode.POSITIVE]:
                _fuzz(operation, mode, tally)  # GETs take no input to violate
        assert httpx.get(f"{base}/health").status_code == 200  # still up after all of it
    finally:
        stop(server)
    sent = sum(count for key, count in tally.items() if key.endswith(" sent"))
    filtered = sum(count for key, count in tally.items() if key.endswith(" filtered"))
    print(f"{sent} requests, {filtered} generated requests filtered, in {time.perf_counter() - start:.0f} s")
    for key, count in sorted(tally.items()):
        print(f"  {key}: {count}")
    assert filtered < sent, tally  # the filter is not most of what was generated
    posts = [label for label in labels if label.startswith("POST")]
    for label in posts:
        assert tally[f"{label} examples accepted"] >= 1, tally
        assert tally[f"{label} negative sent"] >= CASES_PER_OPERATION // 2, tally
    for label in ACCEPTANCE_CHECKED & set(posts):
        # About 60 % of the generated IMU bodies declare a rate whose rows a window lacks (the samples' rule), so
        # per operation the check is held to a number of accepted requests, and "not most filtered" to the run.
        assert tally[f"{label} positive accepted"] >= CASES_PER_OPERATION // 2, tally
    assert len(posts) == 5 and len(labels) == 9, labels


def violates_documented_rule(case) -> bool:  # type: ignore[no-untyped-def]
    """Whether a schema-valid request breaks a rule stated in a field's description (JSON Schema cannot say it)."""
    label, body = f"{case.operation.method.upper()} {case.operation.path}", case.body
    if not isinstance(body, dict):
        return False
    if label == "POST /v1/imu/windows":
        windows = body["windows"]
        return len(windows) > MAX_WINDOWS_PER_REQUEST or not all(map(_window_has_its_rows, windows))
    if label == "POST /v1/imu/assign":
        sensors = body["sensors"]
        windows = [w for s in sensors for w in s["windows"]]
        ids = [s["sensor_id"] for s in sensors]
        worn = body.get("worn_segments")
        return (
            len(windows) > MAX_WINDOWS_PER_REQUEST
            or not all(map(_window_has_its_rows, windows))
            or len(set(ids)) != len(ids)  # "each sensor_id once"
            or (  # a sensor's candidate_segments and worn_segments "must have a segment in common"
                worn is not None
                and any(s.get("candidate_segments") and not set(s["candidate_segments"]) & set(worn) for s in sensors)
            )
        )
    return False


def _window_has_its_rows(window: dict) -> bool:
    """The samples' rule: at the model's rate exactly 128 rows, else ceil(rows * p / q) >= 128 for the polyphase
    factor p / q = 60 / rate with q <= 1000."""
    rate, rows = window.get("sample_rate_hz", MODEL_RATE_HZ), len(window["samples"])
    if np.isclose(rate, MODEL_RATE_HZ):
        return rows == WINDOW_SAMPLES
    factor = Fraction(MODEL_RATE_HZ / rate).limit_denominator(1000)
    return math.ceil(rows * factor.numerator / factor.denominator) >= WINDOW_SAMPLES


def _examples(operation, tally: Counter[str]) -> None:  # type: ignore[no-untyped-def]
    """The documented examples of an operation are accepted."""
    label = f"{operation.method.upper()} {operation.path}"
    for strategy in operation.get_strategies_from_examples():

        @settings(max_examples=1, deadline=None, database=None, suppress_health_check=list(HealthCheck))
        @given(case=strategy)
        def check(case) -> None:  # type: ignore[no-untyped-def]
            response = _send(case, label, "examples", tally)
            assert 200 <= response.status_code < 300, (
                f"{label} example -> {response.status_code}: {response.text[:300]}"
            )
            tally[f"{label} examples accepted"] += 1

        check()


def _fuzz(operation, mode, tally: Counter[str]) -> None:  # type: ignore[no-untyped-def]
    """Valid (positive) or schema-violating (negative) requests for one operation."""
    label = f"{operation.method.upper()} {operation.path}"
    acceptance = mode is schemathesis.GenerationMode.POSITIVE and label in ACCEPTANCE_CHECKED

    @settings(max_examples=CASES_PER_OPERATION, deadline=None, database=None, suppress_health_check=list(HealthCheck))
    @given(case=operation.as_strategy(generation_mode=mode))
    def check(case) -> None:  # type: ignore[no-untyped-def]
        if acceptance:
            broken = violates_documented_rule(case)
            tally[f"{label} {mode.value} filtered"] += broken
            assume(not broken)
        response = _send(case, label, mode.value, tally)
        if acceptance:
            assert 200 <= response.status_code < 300, f"{label} -> {response.status_code}: {response.text[:300]}"
            tally[f"{label} {mode.value} accepted"] += 1

    check()


def _send(case, label: str, mode: str, tally: Counter[str]):  # type: ignore[no-untyped-def]
    """Send ``case``; its answer must be one the document declares (schemathesis' checks), and no 5xx but a
    declared 503."""
    response = case.call()
    tally[f"{label} {mode} sent"] += 1
    declared = set(case.operation.responses.status_codes)
    status = response.status_code
    assert status < 500 or (status == 503 and "503" in declared), f"{label} -> {status}: {response.text[:300]}"
    case.validate_response(response, checks=CHECKS)
    return response
