"""Cut the sample recording in ``examples/ximu3_lowerbody/`` from the data directory.

    python examples/make_sample.py --data-dir ../shared/data

The x-IMU3 lower-body recording (``imu_real/ximu3_lowerbody``, MIT, x-io Technologies): every device's
``Inertial.csv`` rows from ``START_S`` to ``START_S + DURATION_S`` after the last device started, copied byte for
byte with the header row, one file per device named by its serial number (``<serial>.csv``), and the recording's
``LICENSE.md``.
"""

from __future__ import annotations

import argparse
import os
from pathlib import Path

SOURCE = Path("imu_real") / "ximu3_lowerbody"
START_S = 2.0  # the devices are still (a calibration pose) for about the first 2 s
DURATION_S = 10.0
OUT = Path(__file__).resolve().parent / "ximu3_lowerbody"


def device_files(data_dir: Path) -> dict[str, Path]:
    """``Inertial.csv`` of each device folder (``<label> <serial> (UDP)``) by serial number."""
    folders = sorted(p for p in (data_dir / SOURCE).iterdir() if (p / "Inertial.csv").is_file())
    if not folders:
        raise SystemExit(f"make_sample: no <device>/Inertial.csv under {data_dir / SOURCE}")
    return {folder.name.rsplit(" ", 2)[1]: folder / "Inertial.csv" for folder in folders}


def cut(files: dict[str, Path], start_s: float = START_S, duration_s: float = DURATION_S) -> dict[str, bytes]:
    """Each file's header line and its rows whose timestamp (µs, first column) lies in
    ``[t0 + start_s, t0 + start_s + duration_s)``, ``t0`` the latest first timestamp of all files."""
    lines = {serial: path.read_bytes().splitlines(keepends=True) for serial, path in files.items()}
    t0_us = max(int(rows[1].split(b",")[0]) for rows in lines.values())
    low, high = t0_us + start_s * 1e6, t0_us + (start_s + duration_s) * 1e6
    return {
        serial: rows[0] + b"".join(row for row in rows[1:] if low <= int(row.split(b",")[0]) < high)
        for serial, rows in lines.items()
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--data-dir", type=Path, default=os.environ.get("WEARMOCAP_DATA_DIR"))
    parser.add_argument("--out", type=Path, default=OUT)
    args = parser.parse_args()
    if args.data_dir is None:
        parser.error("give --data-dir or set WEARMOCAP_DATA_DIR")
    args.out.mkdir(parents=True, exist_ok=True)
    for serial, text in cut(device_files(args.data_dir)).items():
        path = args.out / f"{serial}.csv"
        path.write_bytes(text)
        print(f"{path}: {len(text.splitlines()) - 1} rows")
    (args.out / "LICENSE.md").write_bytes((args.data_dir / SOURCE / "LICENSE.md").read_bytes())


if __name__ == "__main__":
    main()
