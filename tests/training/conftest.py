"""Fixtures of the training tests: a real MLflow tracking server per test module."""

from __future__ import annotations

import mlflow
import pytest

from benchmarks.servers import start_mlflow_server, stop


@pytest.fixture(scope="module")
def mlflow_server(tmp_path_factory: pytest.TempPathFactory):
    proc, uri = start_mlflow_server(tmp_path_factory.mktemp("mlflow"))
    mp = pytest.MonkeyPatch()
    mp.setenv("MLFLOW_TRACKING_URI", uri)
    mlflow.set_tracking_uri(uri)
    yield uri
    mp.undo()
    stop(proc)


@pytest.fixture(scope="session")
def canonical_cache(tmp_path_factory: pytest.TempPathFactory):
    """One cache of mocap clips on the canonical body for the pose and flex jobs: the second module reads what
    the first computed (training.pose.data.build_motions) where both run in one process (on two test workers each
    builds its own)."""
    return tmp_path_factory.mktemp("canonical_cache")
