"""Shared fixtures. The data directory comes from WEARMOCAP_DATA_DIR (docs/data.md says how to get it).

A test that reads it asks for the ``data_dir`` fixture and is marked ``needs_data`` for it (by the hook below):
without the variable those tests, and only those, skip with the reason; a variable that names no data directory is
an error. Everything else runs on the small files in ``tests/fixtures/`` (``pytest -m "not needs_data"``).
"""

from __future__ import annotations

import os
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
FIXTURES = Path(__file__).resolve().parent / "fixtures"


def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    for item in items:
        if "data_dir" in getattr(item, "fixturenames", ()):  # also through another fixture that asks for it
            item.add_marker(pytest.mark.needs_data)


@pytest.fixture(scope="session")
def data_dir() -> Path:
    from training.data.catalog import resolve_data_dir

    value = os.environ.get("WEARMOCAP_DATA_DIR")
    if not value:
        pytest.skip("needs the data directory: set WEARMOCAP_DATA_DIR (docs/data.md: scripts/get_data.sh)")
    return resolve_data_dir(value)


@pytest.fixture(scope="session")
def kinematics_cache(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return tmp_path_factory.mktemp("kinematics")
