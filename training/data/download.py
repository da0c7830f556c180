"""Rebuild a data directory from the catalogue: fetch each origin file, convert it, check its sha256, write it.

Files whose sha256 already matches are left as they are, so a second run only does what the first did not finish.
A file is written to ``<name>.part`` and renamed when complete. The five MovingReality exports of a trial are fetched
and converted together (one time base). Standard library and numpy (through the li2018 converter) only.
"""

from __future__ import annotations

import csv
import gzip
import hashlib
import http.client
import os
import time
import urllib.error
import urllib.request
import zlib
from collections.abc import Callable, Iterable
from concurrent.futures import ThreadPoolExecutor, as_completed
from dataclasses import dataclass
from pathlib import Path, PurePosixPath

from training.data import li2018_bvh, xsens_mt
from training.data.origins import FileEntry, carried_file, gzip_deterministic

INDEX = "index.csv"
FETCH_ATTEMPTS = 3
FETCH_TIMEOUT_S = 60.0


@dataclass(frozen=True)
class Outcome:
    """What happened to one file: ``written``, ``present`` (its sha256 already matched) or ``failed``."""

    entry: FileEntry
    status: str
    error: str = ""


class FetchError(RuntimeError):
    """An origin file could not be read."""


def resolve_url(url: str, raw_base: str, mirror: str | None) -> str:
    """The URL to read: the catalogue's, or the same path under ``mirror`` in place of ``raw_base``."""
    if not mirror:
        return url
    if not url.startswith(raw_base + "/"):
        raise FetchError(f"expected a URL under {raw_base}/ to map onto the mirror, got {url}")
    return mirror.rstrip("/") + url[len(raw_base) :]


def _retryable(error: Exception) -> bool:
    if isinstance(error, urllib.error.HTTPError):
        return error.code >= 500 or error.code == 429
    reason = getattr(error, "reason", None)
    return not isinstance(reason, FileNotFoundError | PermissionError | IsADirectoryError)


def fetch(url: str) -> bytes:
    """The bytes at ``url`` (https or file); a few tries for network faults, none for a missing file."""
    request = urllib.request.Request(url, headers={"User-Agent": "wearmocap-get-data"})
    for attempt in range(1, FETCH_ATTEMPTS + 1):
        try:
            with urllib.request.urlopen(request, timeout=FETCH_TIMEOUT_S) as response:
                return response.read()
        except (urllib.error.URLError, http.client.HTTPException, TimeoutError, ConnectionError) as error:
            if attempt == FETCH_ATTEMPTS or not _retryable(error):
                raise FetchError(f"could not read {url}: {error}") from error
            time.sleep(2**attempt)
    raise AssertionError("unreachable")


def sha256_hex(data: bytes) -> str:
    return hashlib.sha256(data).hexdigest()


def stored_sha256(path: Path, check: str) -> str | None:
    """sha256 of the file at ``path`` (of its gunzipped content for check ``uncompressed``); None if unreadable."""
    digest = hashlib.sha256()
    try:
        with gzip.open(path, "rb") if check == "uncompressed" else open(path, "rb") as fh:
            while chunk := fh.read(1 << 20):
                digest.update(chunk)
    except (OSError, EOFError, zlib.error):
        return None
    return digest.hexdigest()


def write_atomic(path: Path, data: bytes) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    part = path.with_name(path.name + ".part")
    part.write_bytes(data)
    os.replace(part, path)


def index_of_present_files(index_text: bytes, dest: Path) -> bytes:
    """index.csv restricted to the rows whose file is in ``dest`` (rows kept byte for byte; CRLF line ends)."""
    header, *rows = index_text.split(b"\r\n")
    kept = [row for row in rows if row and (dest / next(csv.reader([row.decode("utf-8")]))[0]).is_file()]
    return b"\r\n".join([header, *kept, b""])


@dataclass(frozen=True)
class Job:
    """One unit of work: a file, or the five files of a MovingReality trial."""

    entries: tuple[FileEntry, ...]


def plan_jobs(entries: Iterable[FileEntry]) -> list[Job]:
    """One job per file, except one per MovingReality trial folder."""
    jobs: list[Job] = []
    trials: dict[str, list[FileEntry]] = {}
    for e in entries:
        if e.transform == "xsens_mt_csv_gz":
            trials.setdefault(str(PurePosixPath(e.path).parent), []).append(e)
        else:
            jobs.append(Job((e,)))
    return jobs + [Job(tuple(group)) for group in trials.values()]


class Builder:
    """Makes the files of a catalogue in ``dest``, reading origins under ``mirror`` in place of ``raw_base`` if given.

    index.csv lists the files that are in ``dest`` when it is written (all of them after a full run, when it is
    checked against its sha256; the rows of the chosen sources after a ``--sources`` run).
    """

    def __init__(self, dest: Path, raw_base: str, mirror: str | None = None):
        self.dest, self.raw_base, self.mirror = dest, raw_base, mirror

    def _read_origin(self, entry: FileEntry) -> bytes:
        return fetch(resolve_url(entry.url, self.raw_base, self.mirror))

    def _content(self, entry: FileEntry) -> bytes:
        """The file's content before any gzip (what its sha256 is checked on)."""
        if entry.transform == "carried":
            return gzip.decompress(carried_file(entry.path).read_bytes())
        data = self._read_origin(entry)
        if entry.transform == "li2018_bvh":
            return li2018_bvh.csv_to_bvh(data.decode("utf-8")).encode("utf-8")
        return data  # copy, gzip

    def _check_and_write(self, entry: FileEntry, content: bytes) -> Outcome:
        actual = sha256_hex(content)
        if actual != entry.sha256:
            origin = resolve_url(entry.url, self.raw_base, self.mirror) if entry.url else carried_file(entry.path)
            return Outcome(entry, "failed", f"sha256 mismatch: expected {entry.sha256}, got {actual} (from {origin})")
        gzipped = entry.check == "uncompressed"
        write_atomic(self.dest / entry.path, gzip_deterministic(content) if gzipped else content)
        return Outcome(entry, "written")

    def _is_present(self, entry: FileEntry) -> bool:
        target = self.dest / entry.path
        return target.is_file() and stored_sha256(target, entry.check) == entry.sha256

    def _write_index(self, entry: FileEntry) -> Outcome:
        """index.csv: the carried copy, checked against its sha256, restricted to the files now in ``dest``."""
        full = gzip.decompress(carried_file(entry.path).read_bytes())
        if sha256_hex(full) != entry.sha256:
            error = (
                f"sha256 mismatch: expected {entry.sha256}, got {sha256_hex(full)} (from {carried_file(entry.path)})"
            )
            return Outcome(entry, "failed", error)
        rows = index_of_present_files(full, self.dest)
        target = self.dest / entry.path
        if target.is_file() and target.read_bytes() == rows:
            return Outcome(entry, "present")
        write_atomic(target, rows)
        return Outcome(entry, "written")

    def run(self, job: Job) -> list[Outcome]:
        if job.entries[0].path == INDEX:
            return [self._write_index(job.entries[0])]
        todo = [e for e in job.entries if not self._is_present(e)]
        done = [Outcome(e, "present") for e in job.entries if e not in todo]
        if not todo:
            return done
        try:
            if len(job.entries) > 1:  # a MovingReality trial: all five exports give the time base
                texts = {e.path: self._read_origin(e).decode("utf-8") for e in job.entries}
                contents = {p: text.encode("utf-8") for p, text in xsens_mt.convert_trial(texts).items()}
            else:
                contents = {todo[0].path: self._content(todo[0])}
        except (FetchError, ValueError, UnicodeDecodeError, OSError) as error:
            reason = f"{type(error).__name__}: {error}"
            if len(job.entries) > 1:
                reason = f"needs all {len(job.entries)} exports of its trial; {reason}"
            return done + [Outcome(e, "failed", reason) for e in todo]
        return done + [self._check_and_write(e, contents[e.path]) for e in todo]


def build_directory(
    jobs: list[Job], builder: Builder, jobs_in_parallel: int, on_outcome: Callable[[Outcome], None]
) -> list[Outcome]:
    """Run ``jobs`` on a thread pool; ``on_outcome`` is called in this thread for each file as it finishes."""
    outcomes: list[Outcome] = []
    with ThreadPoolExecutor(max_workers=max(1, jobs_in_parallel)) as pool:
        futures = [pool.submit(builder.run, job) for job in jobs]
        for future in as_completed(futures):
            for outcome in future.result():
                outcomes.append(outcome)
                on_outcome(outcome)
    return outcomes
