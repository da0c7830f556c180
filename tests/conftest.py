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


# The longest test files, longest first (seconds on two workers, 2026-12-07): scripts/test.sh hands whole files to
# its workers in collection order (``--no-loadscope-reorder``), so these start first and the short ones fill in
# after them, and both workers finish about together. A file not named here keeps its place after them.
LONGEST_FIRST = (
    "tests/training/i2s/test_pipeline.py",  # 232
    "tests/training/flex/test_pipeline.py",  # 152
    "tests/training/pose/test_pipeline.py",  # 127
    "tests/training/i2s/test_train.py",  # 116
    "tests/service/test_e2e.py",  # 111
    "tests/training/test_snapshot.py",  # 90
    "tests/training/pose/test_rig_check.py",  # 52
    "tests/service/test_pose_imu.py",  # 49
    "tests/training/i2s/test_swing.py",  # 45
    "tests/training/test_tracking_server.py",  # 42
    "tests/training/i2s/test_calibration.py",  # 40
    "tests/service/test_fuzz.py",  # 27
)


def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    for item in items:
        if "data_dir" in getattr(item, "fixturenames", ()):  # also through another fixture that asks for it
            item.add_marker(pytest.mark.needs_data)
    rank = {path: i for i, path in enumerate(LONGEST_FIRST)}
    items.sort(key=lambda item: rank.get(item.nodeid.split("::")[0], len(rank)))  # stable: the rest keep their order


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
