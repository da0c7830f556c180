"""Write the recording that the live view (``/dashboard``) streams: a short span of a real trial from the data
directory, as ``service/static/dashboard/recording.json`` (what it holds) and ``recording.bin`` (little-endian
float32).

The trial is ``capacitive_sub01/CSStiffKnee`` (Pearl et al. 2022; treadmill walking with a mock stiff knee): seven
Xsens IMUs on the pelvis, thighs, shanks and feet with their own orientation output, and a capacitive sleeve on each
leg. The dataset is MIT-licensed (© 2024 Owen Douglas Pearl), which allows shipping a snippet with its copyright and
permission notice: the notice goes into ``recording.json`` and beside the file as ``recording.LICENSE``.

    WEARMOCAP_DATA_DIR=../shared/data .venv/bin/python scripts/dashboard_recording.py

``recording.bin`` holds, in this order: the IMUs, ``(sensors, frames, 10)`` at 60 Hz (acc xyz m/s², gyr xyz rad/s,
q_world_sensor w x y z: the rows of a pose stream), then the sleeves, ``(sides, readings, 7)`` at their own rate.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
from pathlib import Path

import numpy as np

from service.core.recordings import CAPACITIVE_CHANNELS, read_capacitive_oriented, read_capacitive_sleeve
from service.core.resample import resample_pose_rows

REPO = Path(__file__).resolve().parents[1]
OUT = REPO / "service" / "static" / "dashboard"
SOURCE, TRIAL = "capacitive_sub01", "CSStiffKnee"
RATE_HZ = 60.0
CITATION = (
    "Pearl O., Rokhmanova N., Dankovich L., Faille S., Bergbreiter S., Halilaj E. (2022), Capacitive Sensing for "
    "Natural Environment Rehabilitation Monitoring, doi:10.21203/rs.3.rs-1902381/v1"
)


def write_recording(data_dir: Path, start_s: float, seconds: float, out: Path = OUT) -> dict:
    """Write ``recording.json`` / ``recording.bin`` / ``recording.LICENSE`` under ``out``; the metadata."""
    sensors = read_capacitive_oriented(data_dir, TRIAL, SOURCE)
    imu = []
    for s in sensors.values():
        rows = resample_pose_rows(s.acc, s.gyr, s.q_world_sensor, s.rate_hz, RATE_HZ)
        imu.append(rows[int(start_s * RATE_HZ) : int((start_s + seconds) * RATE_HZ)])
    frames = min(len(r) for r in imu)
    sleeves, sleeve_rate = [], None
    for side in ("Left", "Right"):
        cs, rate = read_capacitive_sleeve(data_dir, TRIAL, side, SOURCE)
        sleeve_rate = round(rate, 6)
        sleeves.append(cs[int(start_s * rate) : int((start_s + seconds) * rate)])
    readings = min(len(c) for c in sleeves)
    meta = {
        "name": f"{SOURCE}/{TRIAL}",
        "description": f"{SOURCE} {TRIAL}: treadmill walking with a mock stiff knee, {start_s:g}-"
        f"{start_s + seconds:g} s of the trial; seven Xsens IMUs and a capacitive sleeve on each leg",
        "licence": (data_dir / "imu_real" / SOURCE / "LICENSE").read_text(),
        "citation": CITATION,
        "written_by": "scripts/dashboard_recording.py",
        "start_s": start_s,
        "seconds": seconds,
        "imu": {
            "sample_rate_hz": RATE_HZ,
            "frames": frames,
            "values": ["acc_x", "acc_y", "acc_z", "gyr_x", "gyr_y", "gyr_z", "q_w", "q_x", "q_y", "q_z"],
            "units": {"acc": "m/s^2", "gyr": "rad/s", "q_world_sensor": "unit quaternion w, x, y, z (z up)"},
            "sensors": [
                {"sensor_id": s.name.removesuffix("_offset_imu"), "segment": seg} for seg, s in sensors.items()
            ],
        },
        "flex": {
            "sample_rate_hz": sleeve_rate,
            "readings": readings,
            "channels": list(CAPACITIVE_CHANNELS),
            "sides": ["Left", "Right"],
            "joint": "Knee",
        },
    }
    out.mkdir(parents=True, exist_ok=True)
    blob = np.concatenate(
        [np.stack([r[:frames] for r in imu]).ravel(), np.stack([c[:readings] for c in sleeves]).ravel()]
    )
    (out / "recording.bin").write_bytes(blob.astype("<f4").tobytes())
    (out / "recording.json").write_text(json.dumps(meta, indent=1) + "\n")
    shutil.copyfile(data_dir / "imu_real" / SOURCE / "LICENSE", out / "recording.LICENSE")
    return meta


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--data-dir", type=Path, default=os.environ.get("WEARMOCAP_DATA_DIR", "../shared/data"))
    parser.add_argument("--start-s", type=float, default=5.0, help="where the span starts in the trial")
    parser.add_argument("--seconds", type=float, default=25.0, help="how long the span is")
    args = parser.parse_args()
    meta = write_recording(Path(args.data_dir), args.start_s, args.seconds)
    print(f"wrote {OUT / 'recording.bin'}: {meta['imu']['frames']} IMU frames, {meta['flex']['readings']} readings")


if __name__ == "__main__":
    main()
