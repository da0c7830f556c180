"""Schema fuzzing of the OpenAPI document: generated requests (valid and invalid) never get a 5xx.

Driven through schemathesis' Hypothesis strategies (its pytest plugin does not support this pytest)
against a real uvicorn server with tiny ONNX models.
"""

from __future__ import annotations

import shutil
from pathlib import Path

import httpx
import schemathesis
from hypothesis import HealthCheck, given, settings

from benchmarks.servers import start_service, stop
from tests.service.conftest import TINY_POSE, write_tiny_model, write_tiny_pose_model

MODELS = Path(__file__).resolve().parents[2] / "onnx_models"
CASES_PER_OPERATION = 260  # per operation and mode (POSTs: valid and schema-violating): > 1000 cases in all


def test_generated_requests_never_get_a_server_error(tmp_path: Path) -> None:
    root = tmp_path / "onnx_models"
    write_tiny_model(root, "i2s_assignment")
    write_tiny_model(root, "i2s_alignment")
    for task in TINY_POSE:  # the pose routes answer 503 without a pose model; with one they must never 5xx
        write_tiny_pose_model(root, task)
    for name in ("pose_lower3", "pose_lower3_stream"):  # the shipped lower-body pose models, 1.2 / 2.7 MB
        shutil.copytree(MODELS / name, root / name)
    server, base = start_service(root, max_body_bytes="1000000")
    counts: dict[str, int] = {}
    try:
        schema = schemathesis.openapi.from_url(f"{base}/openapi.json")
        for result in schema.get_all_operations():
            operation = result.ok()
            modes = list(schemathesis.GenerationMode) if operation.method.lower() == "post" else []
            for mode in modes or [schemathesis.GenerationMode.POSITIVE]:  # GETs take no input to violate
                _fuzz(operation, mode, counts)
        assert httpx.get(f"{base}/health").status_code == 200  # still up after all of it
    finally:
        stop(server)
    fuzzed = {"POST /v1/imu/windows negative", "POST /v1/imu/assign negative", "POST /v1/pose/flex negative"}
    assert fuzzed | {"POST /v1/pose/imu positive", "POST /v1/pose/imu negative"} <= set(counts)
    assert sum(counts.values()) >= 1000, counts


def _fuzz(operation, mode, counts: dict[str, int]) -> None:  # type: ignore[no-untyped-def]
    """Valid (positive) or schema-violating (negative) requests for one operation."""
    label = f"{operation.method.upper()} {operation.path} {mode.value}"

    @settings(max_examples=CASES_PER_OPERATION, deadline=None, database=None, suppress_health_check=list(HealthCheck))
    @given(case=operation.as_strategy(generation_mode=mode))
    def check(case) -> None:  # type: ignore[no-untyped-def]
        response = case.call()
        counts[label] = counts.get(label, 0) + 1
        assert response.status_code < 500, f"{label} -> {response.status_code}: {response.text[:300]}"

    check()
