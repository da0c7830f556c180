"""Rebuild the data directory from its public origins.

    python -m training.data.get --dest DIR [--sources a,b] [--mirror URL] [--jobs N]

Each file of the catalogue (training/data/files.csv.gz) is downloaded from its origin, a public GitHub repository at a
pinned commit (training/data/sources.toml), converted where the data directory keeps a converted form, checked against
its sha256 and written to DIR/<path>: DIR ends up laid out like the data directory, with its README.md and index.csv.
Files already in DIR with the right sha256 are skipped, so an interrupted run can simply be started again. Every
failed file is listed at the end and the exit status is then 1. Standard library and numpy only (no torch).
"""

from __future__ import annotations

import argparse
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import TextIO

from training.data.download import Builder, Outcome, build_directory, plan_jobs
from training.data.origins import FILES_TABLE, FileEntry, load_catalogue, read_files_table

DIRECTORY_FILES = "(data directory)"  # the label of README.md and index.csv, which belong to no source
MIB = 2**20


@dataclass
class Progress:
    """Running count of files and bytes, printed as a line per source and every ``every`` files."""

    total_files: int
    total_bytes: int
    stream: TextIO = sys.stderr
    every: int = 250
    files: int = 0
    bytes: int = 0
    started: float = field(default_factory=time.monotonic)

    def counter(self) -> str:
        return (
            f"[{self.files}/{self.total_files} files, {self.bytes / MIB:.1f}/{self.total_bytes / MIB:.1f} MiB, "
            f"{time.monotonic() - self.started:.0f} s]"
        )

    def start_source(self, name: str, entries: list[FileEntry]) -> None:
        size = sum(e.bytes for e in entries) / MIB
        print(f"{name}: {len(entries)} files, {size:.1f} MiB {self.counter()}", file=self.stream, flush=True)

    def done(self, outcome: Outcome) -> None:
        self.files += 1
        self.bytes += outcome.entry.bytes
        if self.files % self.every == 0:
            print(f"  {self.counter()}", file=self.stream, flush=True)

    def end_source(self, name: str, outcomes: list[Outcome]) -> None:
        counts = {s: sum(o.status == s for o in outcomes) for s in ("written", "present", "failed")}
        print(
            f"{name}: {counts['written']} written, {counts['present']} already there, {counts['failed']} failed "
            f"{self.counter()}",
            file=self.stream,
            flush=True,
        )


def parse_sources(text: str | None, known: list[str]) -> list[str]:
    if not text:
        return known
    chosen = [name.strip() for name in text.split(",") if name.strip()]
    unknown = [name for name in chosen if name not in known]
    if unknown:
        raise SystemExit(f"--sources: unknown {unknown}; expected a comma-separated subset of {','.join(known)}")
    return [name for name in known if name in chosen]


def mirror_url(text: str | None) -> str | None:
    """``--mirror`` as given, or a local folder turned into its file:// URL."""
    if not text or "://" in text:
        return text
    folder = Path(text).expanduser().resolve()
    if not folder.is_dir():
        raise SystemExit(f"--mirror: expected a URL or an existing folder, got {text}")
    return folder.as_uri()


def parse_args(argv: list[str] | None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(prog="python -m training.data.get", description=__doc__.split("\n\n")[0])
    parser.add_argument("--dest", type=Path, required=True, help="folder to fill (created if absent)")
    parser.add_argument(
        "--sources", help="comma-separated sources to get (default: all); index.csv lists the files in DEST"
    )
    parser.add_argument(
        "--mirror",
        help="base URL (or local folder) that replaces https://raw.githubusercontent.com, laid out as "
        "<owner>/<repository>/<commit>/<path>",
    )
    parser.add_argument("--jobs", type=int, default=8, help="files fetched at once (default 8)")
    parser.add_argument("--table", type=Path, default=FILES_TABLE, help="per-file table (default: %(default)s)")
    return parser.parse_args(argv)


def main(argv: list[str] | None = None, stream: TextIO | None = None) -> int:
    args = parse_args(argv)
    out = stream or sys.stderr
    catalogue = load_catalogue()
    chosen = parse_sources(args.sources, list(catalogue.sources))
    entries = [e for e in read_files_table(args.table) if e.source in chosen or not e.source]
    builder = Builder(args.dest.expanduser().resolve(), catalogue.raw_base, mirror_url(args.mirror))
    progress = Progress(len(entries), sum(e.bytes for e in entries), out)
    print(f"writing {len(entries)} files of {len(chosen)} sources to {builder.dest}", file=out, flush=True)
    failed: list[Outcome] = []
    for name in [*chosen, ""]:  # README.md and index.csv last, and only once every other file is there
        group = [e for e in entries if e.source == name]
        if not name and failed:
            print(f"{DIRECTORY_FILES}: README.md and index.csv are written once every other file is there", file=out)
            break
        label = name or DIRECTORY_FILES
        progress.start_source(label, group)
        outcomes = build_directory(plan_jobs(group), builder, args.jobs, progress.done)
        progress.end_source(label, outcomes)
        failed += [o for o in outcomes if o.status == "failed"]
    if failed:
        print(f"\n{len(failed)} of {len(entries)} files failed:", file=out)
        for o in sorted(failed, key=lambda o: o.entry.path):
            print(f"  {o.entry.path}: {o.error}", file=out)
        print("Run the same command again to retry them; files already written are kept.", file=out, flush=True)
        return 1
    print(f"done: {len(entries)} files in {builder.dest} {progress.counter()}", file=out, flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
