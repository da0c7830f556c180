"""The data directory and its ``index.csv`` (``../shared/data/README.md``).

The directory is configurable: an explicit path, else the ``WEARMOCAP_DATA_DIR`` environment
variable. There is no silent default: a missing setting is an error that says how to set it.
"""

from __future__ import annotations

import csv
import os
import re
from dataclasses import dataclass
from pathlib import Path

DATA_DIR_ENV = "WEARMOCAP_DATA_DIR"

# Length unit of each mocap source in metres (README "Frames, and mapping").
METRES_PER_UNIT = {
    "cmu_li2018": 1.0,
    "cmu_iclone": 0.01,
    "cmu_raw": 0.0254 / 0.45,
    "bandai_namco_1": 0.01,
    "bandai_namco_2": 0.01,
}

# what a model trained on Bandai-Namco's clips carries (its manifest says so)
BANDAI_LICENCE = "CC BY-NC 4.0 (Bandai Namco Research Motiondataset): non-commercial use only"


def is_bandai_namco(source: str) -> bool:
    """Either Bandai-Namco set (``bandai_namco_1``, ``bandai_namco_2``): three unnamed actors, CC BY-NC 4.0."""
    return source.startswith("bandai_namco")


def resolve_data_dir(explicit: str | Path | None = None) -> Path:
    """The data directory: ``explicit`` if given, else ``$WEARMOCAP_DATA_DIR``; must hold index.csv."""
    value = explicit if explicit is not None else os.environ.get(DATA_DIR_ENV)
    if not value:
        raise RuntimeError(
            f"no data directory: pass --data-dir or set {DATA_DIR_ENV} to the folder that holds index.csv "
            "(docs/data.md: scripts/get_data.sh --dest DIR downloads it)"
        )
    path = Path(value).expanduser().resolve()
    if not (path / "index.csv").is_file():
        raise RuntimeError(f"data directory {path} has no index.csv; expected the layout of shared/data")
    return path


@dataclass(frozen=True)
class CatalogEntry:
    path: str  # relative to the data directory
    source: str
    subject: str  # dataset-prefixed id, or "" if unknown
    activity: str
    fps: float
    notes: str
    exclude: str

    @property
    def tpose_frames(self) -> int:
        """Frames to drop at the start (T-pose), parsed from the notes column."""
        match = re.search(r"T-pose at start: first (\d+) frame", self.notes)
        if match:
            return int(match.group(1))
        return 1 if "frame 0 = T-pose" in self.notes else 0

    @property
    def group(self) -> str:
        """Leave-one-subject-out group: the subject id, or one pool for unlabelled li2018 clips."""
        return self.subject or f"{self.source}_unlabelled"


def read_catalog(data_dir: Path) -> list[CatalogEntry]:
    with open(data_dir / "index.csv", newline="") as fh:
        return [
            CatalogEntry(
                r["path"], r["source"], r["subject"], r["activity"], float(r["fps"] or 0), r["notes"], r["exclude"]
            )
            for r in csv.DictReader(fh)
        ]


def mocap_entries(
    data_dir: Path, activities: list[str] | None = None, sources: list[str] | None = None
) -> list[CatalogEntry]:
    """Usable BVH clips (``exclude`` empty), plain or gzipped, optionally restricted to activities and sources."""
    return [
        e
        for e in read_catalog(data_dir)
        if e.path.endswith((".bvh", ".bvh.gz"))
        and not e.exclude
        and (activities is None or e.activity in activities)
        and (sources is None or e.source in sources)
    ]
