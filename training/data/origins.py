"""The data catalogue: ``sources.toml`` (one entry per source) and ``files.csv.gz`` (one row per file).

Both live beside this module. ``files.csv.gz`` has the columns of ``FILES_COLUMNS``: the file's path in the data
directory, its source (blank for the directory's own README.md and index.csv), the transform that makes it from its
origin file (see sources.toml), what the sha256 is taken of (``file``: the file as stored; ``uncompressed``: the
gunzipped content of a ``.gz`` file, because gzip output differs between implementations), the sha256, the size in
bytes as stored, and the origin URL (blank for ``carried`` files). Standard library only.
"""

from __future__ import annotations

import csv
import gzip
import io
import tomllib
from dataclasses import dataclass
from pathlib import Path
from typing import Any
from urllib.parse import quote

CATALOGUE_DIR = Path(__file__).resolve().parent
SOURCES_TOML = CATALOGUE_DIR / "sources.toml"
FILES_TABLE = CATALOGUE_DIR / "files.csv.gz"
CARRIED_DIR = CATALOGUE_DIR / "carried"
FILES_COLUMNS = ("path", "source", "transform", "check", "sha256", "bytes", "url")
TRANSFORMS = ("copy", "gzip", "li2018_bvh", "xsens_mt_csv_gz", "carried")
CHECKS = ("file", "uncompressed")


@dataclass(frozen=True)
class Origin:
    """A public repository at a pinned commit."""

    key: str
    repository: str  # owner/name on GitHub
    commit: str
    licence: str

    def url(self, raw_base: str, path: str) -> str:
        """Raw download URL of ``path`` (as it is named in the repository) at the pinned commit."""
        return f"{raw_base}/{self.repository}/{self.commit}/{quote(path, safe='/()')}"


@dataclass(frozen=True)
class Source:
    """One value of index.csv's ``source`` column; ``facts`` holds the rest of its sources.toml entry."""

    name: str
    dir: str  # relative to the data directory
    origins: tuple[str, ...]
    facts: dict[str, Any]


@dataclass(frozen=True)
class FileEntry:
    """One row of files.csv.gz."""

    path: str
    source: str
    transform: str
    check: str
    sha256: str
    bytes: int
    url: str


@dataclass(frozen=True)
class Catalogue:
    raw_base: str
    cmu: dict[str, str]
    origins: dict[str, Origin]
    sources: dict[str, Source]


def load_catalogue(path: Path = SOURCES_TOML) -> Catalogue:
    """Read sources.toml; every source must name origins that it defines."""
    with open(path, "rb") as fh:
        raw = tomllib.load(fh)
    origins = {
        key: Origin(key, o["repository"], o["commit"], o["licence"]) for key, o in raw.get("origins", {}).items()
    }
    sources = {}
    for name, s in raw.get("sources", {}).items():
        unknown = [key for key in s["origins"] if key not in origins]
        if unknown:
            raise ValueError(f"{path}: source {name} names origins {unknown}; expected some of {sorted(origins)}")
        rest = {k: v for k, v in s.items() if k not in ("dir", "origins")}
        sources[name] = Source(name, s["dir"], tuple(s["origins"]), rest)
    return Catalogue(raw["raw_base"].rstrip("/"), dict(raw.get("cmu", {})), origins, sources)


def read_files_table(path: Path = FILES_TABLE) -> list[FileEntry]:
    """Read files.csv.gz, checking its columns and the transform and check values."""
    with gzip.open(path, "rt", newline="", encoding="utf-8") as fh:
        reader = csv.DictReader(fh)
        if tuple(reader.fieldnames or ()) != FILES_COLUMNS:
            raise ValueError(f"{path}: expected columns {FILES_COLUMNS}, found {reader.fieldnames}")
        entries = [FileEntry(**{**row, "bytes": int(row["bytes"])}) for row in reader]
    for e in entries:
        if e.transform not in TRANSFORMS or e.check not in CHECKS:
            raise ValueError(
                f"{path}: {e.path} has transform {e.transform!r} and check {e.check!r}; "
                f"expected one of {TRANSFORMS} and one of {CHECKS}"
            )
    return entries


def gzip_deterministic(data: bytes) -> bytes:
    """gzip with mtime 0 and no file name, so the same input always gives the same bytes here."""
    return gzip.compress(data, compresslevel=9, mtime=0)


def write_files_table(entries: list[FileEntry], path: Path = FILES_TABLE) -> None:
    buffer = io.StringIO()
    writer = csv.writer(buffer, lineterminator="\n")
    writer.writerow(FILES_COLUMNS)
    for e in entries:
        writer.writerow([e.path, e.source, e.transform, e.check, e.sha256, e.bytes, e.url])
    path.write_bytes(gzip_deterministic(buffer.getvalue().encode("utf-8")))


def carried_file(path: str) -> Path:
    """This repository's gzipped copy of a ``carried`` file of the data directory."""
    return CARRIED_DIR / f"{path}.gz"
