"""OpenSim storage files (``.mot`` / ``.sto``, version 1): a header of ``key=value`` lines up to ``endheader``,
then a tab-separated table whose first column is time. The capacitive sleeves are published so, and flex answers
can be written so for OpenSim's tools."""

from __future__ import annotations

import numpy as np


def storage_cells(text: str, where: str) -> tuple[dict[str, str], list[str], list[list[str]]]:
    """A storage file's header (``key=value`` lines), column names and rows of cells as written (``.sto`` cells may
    hold several comma-separated numbers, a quaternion)."""
    lines = text.splitlines()
    try:
        head = next(k for k, line in enumerate(lines) if line.strip() == "endheader")
    except StopIteration:
        raise ValueError(f"{where}: expected an 'endheader' line closing the header, found none") from None
    if head + 1 >= len(lines):
        raise ValueError(f"{where}: expected the column names after 'endheader', found the end of the file")
    header = dict(line.split("=", 1) for line in lines[:head] if "=" in line)
    names = lines[head + 1].split("\t")
    rows = [line.split("\t") for line in lines[head + 2 :] if line.strip()]
    for k, row in enumerate(rows):
        if len(row) != len(names):
            raise ValueError(f"{where}: row {k} has {len(row)} cells where the header names {len(names)} columns")
    return header, names, rows


def read_opensim_storage(text: str, where: str) -> tuple[dict[str, str], list[str], np.ndarray]:
    """A storage file of numbers: its header, column names (time first) and rows ``(T, columns)``."""
    header, names, rows = storage_cells(text, where)
    try:
        return header, names, np.array(rows, dtype=np.float64).reshape(len(rows), len(names))
    except ValueError:
        raise ValueError(f"{where}: expected numbers in every cell") from None


def format_opensim_storage(name: str, time_s: np.ndarray, columns: dict[str, np.ndarray], in_degrees: bool) -> str:
    """The text of a storage file that ``read_opensim_storage`` and OpenSim read: ``name``, the header, then a
    tab-separated table with ``time`` first and ``columns`` in their order."""
    table = np.column_stack([time_s, *columns.values()])
    lines = [
        name,
        "version=1",
        f"nRows={len(table)}",
        f"nColumns={table.shape[1]}",
        f"inDegrees={'yes' if in_degrees else 'no'}",
        "endheader",
        "\t".join(["time", *columns]),
    ]
    lines += ["\t".join(f"{v:.6f}" for v in row) for row in table]
    return "\n".join(lines) + "\n"
