"""The team tracking server for real (``training.tracking_server``): PostgreSQL, an S3 store (moto's server) and
``mlflow server`` as processes on loopback ports; a training job of this project (the CLI, as a user runs it)
logs to it and registers its model; the server's REST API and the bucket hold what it logged; the service (a
real uvicorn process, without mlflow) serves that model by its registry alias."""

from __future__ import annotations

import hashlib
import math
import os
import shutil
import subprocess
import sys
import tempfile
from collections.abc import Iterator
from pathlib import Path

import boto3
import httpx
import pytest
import yaml

from benchmarks.servers import free_port, start_process, stop
from service.core.manifest import MLMODEL_METADATA_KEY
from service.core.recordings import read_capacitive_sleeve
from training.tracking_server import TrackingStack, find_postgres_bin, tracking_stack

REPO = Path(__file__).resolve().parents[2]
MODEL = "flex_capacitive_knee"  # the configuration's name: the registered model
# The capacitive knee job (real sleeves, seconds of training): one epoch of 64 windows on a small network.
JOB = [
    "capacitive-train",
    "training/configs/flex_capacitive_knee.yaml",
    *("-s", "train.windows_per_epoch=64", "-s", "train.max_epochs=1", "-s", "tracking.experiment=team"),
    *("-s", "model.bilstm_sizes=[16,32,32,32,16]"),
]

pytestmark = pytest.mark.skipif(
    find_postgres_bin() is None,
    reason="PostgreSQL binaries (initdb, postgres) not found on the PATH or in /usr/lib/postgresql/<major>/bin: "
    "apt-get install postgresql",
)


@pytest.fixture(scope="module")
def stack() -> Iterator[TrackingStack]:
    root = Path(tempfile.mkdtemp(prefix="wearmocap-team-"))
    root.chmod(0o755)  # run as root, PostgreSQL runs as its own OS user and must reach its cluster here
    try:
        with tracking_stack(root, durable=False) as started:
            yield started
    finally:
        shutil.rmtree(root, ignore_errors=True)


@pytest.fixture(scope="module")
def run(stack: TrackingStack, data_dir: Path) -> dict:
    """The job's run as the tracking server's REST API returns it."""
    env = {**os.environ, "MLFLOW_TRACKING_URI": stack.tracking_uri, "WEARMOCAP_DATA_DIR": str(data_dir)}
    done = subprocess.run(
        [sys.executable, "-m", "training.cli", *JOB], cwd=REPO, env=env, capture_output=True, text=True, timeout=240
    )
    assert done.returncode == 0, done.stderr[-3000:]
    run_id = done.stdout.strip().rsplit("run ", 1)[1]
    return api(stack, "runs/get", run_id=run_id)["run"]


def api(stack: TrackingStack, endpoint: str, **params: str) -> dict:
    """GET ``/api/2.0/mlflow/<endpoint>`` of the tracking server (its REST API, no mlflow client)."""
    r = httpx.get(f"{stack.tracking_uri}/api/2.0/mlflow/{endpoint}", params=params, timeout=10)
    assert r.status_code == 200, r.text
    return r.json()


def proxied(stack: TrackingStack, location: str, name: str) -> bytes:
    """An artifact downloaded through the tracking server (``mlflow-artifacts:/<path>`` locations)."""
    path = location.removeprefix("mlflow-artifacts:").lstrip("/")
    r = httpx.get(f"{stack.tracking_uri}/api/2.0/mlflow-artifacts/artifacts/{path}/{name}", timeout=10)
    assert r.status_code == 200, r.text
    return r.content


def bucket_object(stack: TrackingStack, location: str, name: str) -> bytes:
    """The same artifact read from the S3 bucket directly (the server's artifact root is the bucket's root)."""
    env = stack.s3_env()
    s3 = boto3.client(
        "s3",
        endpoint_url=stack.s3_endpoint_url,
        aws_access_key_id=env["AWS_ACCESS_KEY_ID"],
        aws_secret_access_key=env["AWS_SECRET_ACCESS_KEY"],
        region_name=env["AWS_DEFAULT_REGION"],
    )
    key = f"{location.removeprefix('mlflow-artifacts:').strip('/')}/{name}"
    return s3.get_object(Bucket=stack.bucket, Key=key)["Body"].read()


def test_the_run_is_in_postgresql_with_its_params_and_metrics(stack: TrackingStack, run: dict) -> None:
    assert stack.backend_store_uri.startswith("postgresql+psycopg2://")
    assert run["info"]["status"] == "FINISHED" and run["info"]["run_name"] == MODEL
    params = {p["key"]: p["value"] for p in run["data"]["params"]}
    assert params["train.windows_per_epoch"] == "64" and params["train.max_epochs"] == "1"
    metrics = {m["key"]: m["value"] for m in run["data"]["metrics"]}
    for key in ("val_mae_deg", "test_mae_deg", "test_left_knee_mae_deg", "train_wall_time_s"):
        assert math.isfinite(metrics[key]), key
    assert 0 < metrics["test_mae_deg"] < 90
    experiment = api(stack, "experiments/get-by-name", experiment_name="team")["experiment"]
    assert experiment["experiment_id"] == run["info"]["experiment_id"]


def test_the_artifacts_are_listed_by_the_server_and_stored_in_the_bucket(stack: TrackingStack, run: dict) -> None:
    run_id, location = run["info"]["run_id"], run["info"]["artifact_uri"]
    assert location.startswith("mlflow-artifacts:/")  # proxied: clients need the server's URL only
    listed = api(stack, "artifacts/list", run_id=run_id, path="plots")["files"]
    assert {"plots/learning_curve.png", "plots/trace_test.png"} <= {f["path"] for f in listed}
    summary = proxied(stack, location, "evaluation/summary.json")
    assert bucket_object(stack, location, "evaluation/summary.json") == summary
    assert yaml.safe_load(summary)["run_id"] == run_id
    png = bucket_object(stack, location, "plots/learning_curve.png")
    assert png.startswith(b"\x89PNG") and len(png) == next(f["file_size"] for f in listed if "learning" in f["path"])


def test_the_model_is_registered_with_its_alias_and_its_file_is_in_the_bucket(stack: TrackingStack, run: dict) -> None:
    version = api(stack, "registered-models/alias", name=MODEL, alias="champion")["model_version"]
    assert version["version"] == "1" and version["run_id"] == run["info"]["run_id"]
    assert version["status"] == "READY"
    model = api(stack, "registered-models/get", name=MODEL)["registered_model"]
    assert {"alias": "champion", "version": "1"} in model["aliases"]
    location = api(stack, "model-versions/get-download-uri", name=MODEL, version="1")["artifact_uri"]
    manifest = yaml.safe_load(proxied(stack, location, "MLmodel"))["metadata"][MLMODEL_METADATA_KEY]
    onnx_bytes = bucket_object(stack, location, "model.onnx")
    assert hashlib.sha256(onnx_bytes).hexdigest() == manifest["sha256"]
    assert manifest["mlflow"]["run_id"] == run["info"]["run_id"]


def test_the_service_serves_the_model_by_its_alias_from_the_server(
    stack: TrackingStack, run: dict, data_dir: Path, tmp_path: Path
) -> None:
    settings = {
        "WEARMOCAP_MODELS_DIR": str(tmp_path / "no_local_models"),
        "WEARMOCAP_INFERENCE_THREADS": "1",
        "WEARMOCAP_MLFLOW_TRACKING_URI": stack.tracking_uri,
        "WEARMOCAP_REGISTRY_MODELS": f"models:/{MODEL}@champion",
        "WEARMOCAP_REGISTRY_CACHE_DIR": str(tmp_path / "registry_cache"),
    }
    port = free_port()  # /health: /ready waits for an assignment model, which this service does not have
    proc, base = start_process([sys.executable, "-m", "service", "--port", str(port)], "/health", port, settings)
    try:
        served = httpx.get(f"{base}/v1/models", timeout=10).json()[MODEL]
        assert served["source"] == f"models:/{MODEL}@champion (version 1) at {stack.tracking_uri}"
        assert served["mlflow"]["run_id"] == run["info"]["run_id"]
        readings, rate_hz = read_capacitive_sleeve(data_dir, "CSStiffKnee", "Left")
        block = readings[: int(10 * rate_hz)]
        r = httpx.post(f"{base}/v1/pose/flex", json={"samples": block.tolist(), "sample_rate_hz": rate_hz}, timeout=30)
        assert r.status_code == 200, r.text
        body = r.json()
        at_model_rate = round(len(block) * body["sample_rate_hz"] / rate_hz)  # resampled to the model's rate
        answered = at_model_rate - body["first_sample"] - body["latency_samples"]  # a median layer: one behind
        assert body["model"]["name"] == MODEL and body["frames"] == answered
        knee = [v for joint in body["angles_deg"].values() for v in joint["flexion"]]
        assert len(knee) == body["frames"] and all(math.isfinite(v) for v in knee)
    finally:
        stop(proc)
