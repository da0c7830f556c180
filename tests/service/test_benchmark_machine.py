"""The machine reference every benchmark records (benchmarks/machine.py)."""

from __future__ import annotations

import shutil
from pathlib import Path

from benchmarks.machine import machine_state
from benchmarks.servers import REPO, served_dir


def test_the_machine_state_times_the_served_i2s_files_and_names_them() -> None:
    state = machine_state(REPO / "onnx_models", "start")
    assert state["when"] == "start" and state["cores"] >= 1
    assert state["per_core_windows_per_s"] > 0
    assert state["models"] == {
        "i2s_assignment": served_dir("i2s_assignment").name,
        "i2s_alignment": served_dir("i2s_alignment").name,
    }


def test_the_machine_state_says_what_is_missing_without_the_reference_models(tmp_path: Path) -> None:
    shutil.copytree(served_dir("i2s_assignment"), tmp_path / "i2s_assignment" / served_dir("i2s_assignment").name)
    state = machine_state(tmp_path, "end")  # at a benchmark's end: its results must still be written
    assert state["when"] == "end" and state["per_core_windows_per_s"] is None and state["missing"] == ["i2s_alignment"]
