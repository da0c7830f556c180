"""Shared fixtures. The data directory comes from WEARMOCAP_DATA_DIR (README 'Tests'); tests that read
real data fail with a clear message when it is missing instead of skipping."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="session")
def data_dir() -> Path:
    from training.data.catalog import resolve_data_dir

    return resolve_data_dir(os.environ.get("WEARMOCAP_DATA_DIR"))


@pytest.fixture(scope="session")
def kinematics_cache(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return tmp_path_factory.mktemp("kinematics")
