"""OpenSim storage files: what is written reads back, and a file that is not one says why."""

from __future__ import annotations

import numpy as np
import pytest

from service.core.opensim import format_opensim_storage, read_opensim_storage


def test_an_opensim_storage_file_reads_back_as_written() -> None:
    t = np.arange(5) / 50.0
    cols = {"Knee_flexion": np.array([0.0, 12.5, 30.25, -1.0, 7.123456]), "Hip_flexion": np.linspace(0, 1, 5)}
    header, names, table = read_opensim_storage(format_opensim_storage("walk", t, cols, in_degrees=True), "a.mot")
    assert header == {"version": "1", "nRows": "5", "nColumns": "3", "inDegrees": "yes"}
    assert names == ["time", "Knee_flexion", "Hip_flexion"]
    np.testing.assert_allclose(table, np.column_stack([t, *cols.values()]), atol=1e-6)


@pytest.mark.parametrize(
    "text, fragment",
    [
        ("walk\nversion=1\ntime\tx\n0\t1\n", "expected an 'endheader'"),
        ("walk\nendheader\n", "expected the column names"),
        ("walk\nendheader\ntime\tx\n0\t1\t2\n", "row 0 has 3 cells where the header names 2"),
        ("walk\nendheader\ntime\tx\n0\tbent\n", "expected numbers"),
    ],
)
def test_a_file_that_is_not_a_storage_file_is_named_with_what_was_expected(text: str, fragment: str) -> None:
    with pytest.raises(ValueError, match=fragment) as exc:
        read_opensim_storage(text, "b.mot")
    assert str(exc.value).startswith("b.mot: ")
