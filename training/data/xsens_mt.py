"""Xsens MT Manager text export -> the compact CSV of ``imu_real/movingreality`` (data README, its section).

Input: ``MT_<station>_<trial>-000_<device>.txt`` as MT Manager 2019.2 writes it: ``//`` comment lines, one
tab-separated header line (``PacketCounter SampleTimeFine Acc_X … Quat_q0 … Yaw``), then one tab-separated row per
sample. ``SampleTimeFine`` is empty in these exports, so time comes from the 16-bit ``PacketCounter``.

Output: ``time_s,acc_x_mps2,acc_y_mps2,acc_z_mps2,gyr_x_rads,gyr_y_rads,gyr_z_rads,q_w,q_x,q_y,q_z`` with
time_s = (PacketCounter - the trial's first PacketCounter) / 100 (counter unwrapped at 65536; the five sensors of a
trial share the Awinda station's counter), acc (``Acc_*``) with 4 decimals, gyr (``Gyr_*``) with 5, the quaternion
(``Quat_q0..q3``, scalar first, sensor -> ENU) with 6. Rows with an empty or NaN value are left out. Every stored file
is reproduced byte for byte.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass

SAMPLE_RATE_HZ = 100
COUNTER_MODULUS = 65536
CSV_HEADER = "time_s,acc_x_mps2,acc_y_mps2,acc_z_mps2,gyr_x_rads,gyr_y_rads,gyr_z_rads,q_w,q_x,q_y,q_z"
# (export column, decimals) in output order after time_s
VALUE_COLUMNS = (
    ("Acc_X", 4),
    ("Acc_Y", 4),
    ("Acc_Z", 4),
    ("Gyr_X", 5),
    ("Gyr_Y", 5),
    ("Gyr_Z", 5),
    ("Quat_q0", 6),
    ("Quat_q1", 6),
    ("Quat_q2", 6),
    ("Quat_q3", 6),
)


@dataclass(frozen=True)
class MtExport:
    """One export's converted channels: ``counter`` unwrapped (length T), ``values`` (T, 10) in VALUE_COLUMNS order."""

    counter: list[int]
    values: list[list[float]]


def read_mt_export(text: str) -> MtExport:
    """Parse an MT Manager text export; rows with an empty or NaN value in a converted column are left out."""
    lines = [line for line in text.splitlines() if line.strip() and not line.startswith("//")]
    if not lines:
        raise ValueError("expected a tab-separated header line after the // comments, found no lines")
    header = lines[0].rstrip("\r").split("\t")
    wanted = ["PacketCounter"] + [name for name, _ in VALUE_COLUMNS]
    missing = [name for name in wanted if name not in header]
    if missing:
        raise ValueError(f"expected MT Manager columns {wanted}; missing {missing} in header {header}")
    index = [header.index(name) for name in wanted]
    counter: list[int] = []
    values: list[list[float]] = []
    for line in lines[1:]:
        cells = line.rstrip("\r").split("\t")
        picked = [cells[i].strip() if i < len(cells) else "" for i in index]
        if any(cell == "" or cell.lower() == "nan" for cell in picked):
            continue
        raw = int(picked[0])
        counter.append(raw if not counter else counter[-1] + (raw - counter[-1]) % COUNTER_MODULUS)
        values.append([float(cell) for cell in picked[1:]])
    if not counter:
        raise ValueError("expected at least one complete sample row, found none")
    return MtExport(counter, values)


def start_offsets(first_counters: list[int]) -> list[int]:
    """Samples from the trial's first packet to each file's first packet (16-bit counters, compared circularly)."""
    half = COUNTER_MODULUS // 2
    ahead = [(c - first_counters[0] + half) % COUNTER_MODULUS - half for c in first_counters]
    return [a - min(ahead) for a in ahead]


def export_to_csv(export: MtExport, start_offset: int = 0) -> str:
    """One export as the compact CSV text; ``start_offset`` is its first packet's place after the trial's first."""
    lines = [CSV_HEADER]
    first = export.counter[0]
    for count, row in zip(export.counter, export.values, strict=True):
        time_s = (count - first + start_offset) / SAMPLE_RATE_HZ
        cells = [f"{time_s:.2f}"] + [f"{v:.{decimals}f}" for v, (_, decimals) in zip(row, VALUE_COLUMNS, strict=True)]
        lines.append(",".join(cells))
    return "\n".join(lines) + "\n"


def convert_trial(exports: Mapping[str, str]) -> dict[str, str]:
    """The files of one trial: {name: export text} -> {name: CSV text}, times from the trial's first packet."""
    parsed = {name: read_mt_export(text) for name, text in exports.items()}
    offsets = start_offsets([export.counter[0] for export in parsed.values()])
    return {name: export_to_csv(export, offset) for (name, export), offset in zip(parsed.items(), offsets, strict=True)}
