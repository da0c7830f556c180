"""Regenerate the per-file catalogue (files.csv.gz) and the carried files from a data directory.

    python -m training.data.build_catalogue --data-dir ../shared/data

Every file under the directory gets a row of files.csv.gz: its sha256 as it sits there (of the uncompressed content
for ``.gz`` files), its size, and the URL of its origin file at the pinned commit, found with the naming rules of its
source (``origin_paths`` in sources.toml; the li2018 CSV and the MovingReality export are also named in index.csv's
notes, and the two must agree). The data directory's README.md and index.csv, and the MovingReality README.md, have
no origin: gzipped copies go to training/data/carried/. Standard library only.
"""

from __future__ import annotations

import argparse
import csv
import gzip
import hashlib
import logging
import re
import sys
from collections import Counter
from collections.abc import Callable
from pathlib import Path

from training.data.origins import (
    FILES_TABLE,
    Catalogue,
    FileEntry,
    carried_file,
    gzip_deterministic,
    load_catalogue,
    write_files_table,
)

logger = logging.getLogger(__name__)

CARRIED = ("README.md", "index.csv", "imu_real/movingreality/README.md")
# A rule maps a path inside the source's folder (and its index.csv notes) to (origin key, origin path, transform).
Rule = Callable[[str, str], tuple[str, str, str]]


def _li2018(rel: str, notes: str) -> tuple[str, str, str]:
    if rel == "LICENSE_repo_MIT.txt":
        return "li2018", "LICENSE", "copy"
    match = re.fullmatch(r"([a-z_]+)/(train|test)_([a-z_]+_\d+)\.bvh", rel)
    noted = re.search(r"csv=([^;\s]+)", notes)
    if not match or not noted:
        raise ValueError(f"cmu_li2018/{rel}: expected <action>/<split>_<name>.bvh with csv=... in its notes")
    action, split, name = match.groups()
    csv_path = f"{split}/{action}/{name}.txt"
    if noted.group(1) != csv_path:
        raise ValueError(f"cmu_li2018/{rel}: the name gives {csv_path}, the notes say {noted.group(1)}")
    return "li2018", f"data/cmu_mocap/{csv_path}", "li2018_bvh"


def _iclone(rel: str, notes: str) -> tuple[str, str, str]:
    renamed = {"CMU_data.csv": "CMU data.csv", "README_upstream.md": "README.md"}
    if rel in renamed:
        return "iclone", renamed[rel], "copy"
    match = re.fullmatch(r"(\d\d)_(\d\d)\.bvh", rel)
    if not match:
        raise ValueError(f"cmu_iclone/{rel}: expected SS_TT.bvh")
    subject, trial = match.groups()
    return "iclone", f"All_BVH/subjects/0{subject}/0{subject}_{trial}.bvh", "copy"


def _cmu_raw(rel: str, notes: str) -> tuple[str, str, str]:
    table = {
        "131_01.bvh": ("bvh11", "resources/131_01.bvh"),
        "131_02.bvh": ("bvh11", "resources/131_02.bvh"),
        "131_03.bvh": ("bvh11", "resources/131_03.bvh"),
        "LICENSE_bvh11_repo_MIT.txt": ("bvh11", "LICENSE"),
        "01_01.bvh": ("fairmotion", "tests/data/01_01.bvh"),
        "LICENSE_fairmotion_repo_BSD.txt": ("fairmotion", "LICENSE"),
    }
    return (*table[rel], "copy")


def _bandai(dataset: str) -> Rule:
    root = f"dataset/Bandai-Namco-Research-Motiondataset-{dataset}"

    def rule(rel: str, notes: str) -> tuple[str, str, str]:
        if rel.endswith(".bvh.gz"):
            return "bandai_namco", f"{root}/data/{rel[: -len('.gz')]}", "gzip"
        if rel.endswith(".json"):
            return "bandai_namco", f"{root}/data/{rel}", "copy"
        return "bandai_namco", f"{root}/{rel}", "copy"

    return rule


def _under(key: str, folder: str, kept: tuple[str, ...]) -> Rule:
    def rule(rel: str, notes: str) -> tuple[str, str, str]:
        return key, rel if rel in kept else f"{folder}/{rel}", "copy"

    return rule


def _movingreality(rel: str, notes: str) -> tuple[str, str, str]:
    if rel == "LICENSE":
        return "movingreality", "LICENSE", "copy"
    participant = re.fullmatch(r"(pp\d\d)/\w+/\w+\.csv\.gz", rel)
    export = re.search(r"= Xsens (exported\d+)", notes)
    mt_file = re.search(r"source (MT_\S+\.txt)", notes)
    if not (participant and export and mt_file):
        raise ValueError(f"movingreality/{rel}: expected ppNN/<trial>/<segment>.csv.gz with its export in the notes")
    path = f"data/1019_{participant.group(1)}/Xsens/{export.group(1)}/{mt_file.group(1)}"
    return "movingreality", path, "xsens_mt_csv_gz"


RULES: dict[str, Rule] = {
    "cmu_li2018": _li2018,
    "cmu_iclone": _iclone,
    "cmu_raw": _cmu_raw,
    "bandai_namco_1": _bandai("1"),
    "bandai_namco_2": _bandai("2"),
    "capacitive_sub01": _under("capacitive", "ShankAndThighExperiments/Sub01", ("LICENSE", "ReadMe.txt")),
    "ximu3_lowerbody": _under("ximu3", "Examples/logged_lower_body", ("LICENSE.md",)),
    "gaitmap_foot": _under("gaitmap", "example_data", ("LICENSE",)),
    "movingreality": _movingreality,
}


def content_sha256(path: Path) -> str:
    """sha256 of the file, of its uncompressed content for ``.gz``."""
    digest = hashlib.sha256()
    opener = gzip.open if path.suffix == ".gz" else open
    with opener(path, "rb") as fh:
        while chunk := fh.read(1 << 20):
            digest.update(chunk)
    return digest.hexdigest()


def catalogue_entry(catalogue: Catalogue, data_dir: Path, rel: str, notes: str) -> FileEntry:
    check = "uncompressed" if rel.endswith(".gz") else "file"
    size, sha = (data_dir / rel).stat().st_size, content_sha256(data_dir / rel)
    owner = [s for s in catalogue.sources.values() if rel.startswith(s.dir + "/")]
    source = owner[0].name if owner else ""
    if rel in CARRIED:
        return FileEntry(rel, source, "carried", check, sha, size, "")
    if not owner:
        raise ValueError(f"{rel}: under no source folder of sources.toml")
    key, origin_path, transform = RULES[source](rel[len(owner[0].dir) + 1 :], notes)
    url = catalogue.origins[key].url(catalogue.raw_base, origin_path)
    return FileEntry(rel, source, transform, check, sha, size, url)


def build(data_dir: Path) -> list[FileEntry]:
    """Catalogue every file of ``data_dir``; check that index.csv's rows and sources are all covered."""
    catalogue = load_catalogue()
    with open(data_dir / "index.csv", newline="", encoding="utf-8") as fh:
        index = {row["path"]: row for row in csv.DictReader(fh)}
    unknown_sources = {row["source"] for row in index.values()} - set(catalogue.sources)
    if unknown_sources:
        raise ValueError(f"index.csv has sources {sorted(unknown_sources)} that sources.toml does not describe")
    files = sorted(p.relative_to(data_dir).as_posix() for p in data_dir.rglob("*") if p.is_file())
    missing = sorted(set(index) - set(files))
    if missing:
        raise ValueError(f"index.csv names {len(missing)} files that are not in {data_dir}: {missing[:5]}")
    entries = [catalogue_entry(catalogue, data_dir, rel, index.get(rel, {}).get("notes", "")) for rel in files]
    for e in entries:
        if e.path in index and index[e.path]["source"] != e.source:
            raise ValueError(f"{e.path}: index.csv says source {index[e.path]['source']}, its folder says {e.source}")
    return entries


def write(entries: list[FileEntry], data_dir: Path, table: Path = FILES_TABLE) -> None:
    write_files_table(entries, table)
    for e in entries:
        if e.transform == "carried":
            target = carried_file(e.path)
            target.parent.mkdir(parents=True, exist_ok=True)
            target.write_bytes(gzip_deterministic((data_dir / e.path).read_bytes()))


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m training.data.build_catalogue", description=__doc__.split("\n")[0])
    parser.add_argument("--data-dir", type=Path, required=True, help="the data directory (the one with index.csv)")
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    entries = build(args.data_dir)
    write(entries, args.data_dir)
    counts = Counter((e.source or "(directory)", e.transform) for e in entries)
    for (source, transform), n in sorted(counts.items()):
        logger.info("%-18s %-16s %5d files", source, transform, n)
    logger.info("%d files, %.1f MiB; wrote %s", len(entries), sum(e.bytes for e in entries) / 2**20, FILES_TABLE)
    return 0


if __name__ == "__main__":
    sys.exit(main())
