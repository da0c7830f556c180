"""A team MLflow tracking server on one machine: PostgreSQL holds the runs and the model registry, an
S3-compatible store holds the artifacts, and ``mlflow server`` serves both. The server proxies every artifact
upload and download (``mlflow-artifacts:/`` locations), so its clients (training jobs, the service) need only its
URL, never the database or S3 credentials.

    python -m training.tracking_server --root .cache/team-tracking --port 5000

starts PostgreSQL (a cluster under ``<root>/postgres``, created on first use), an S3 store (moto's server,
in memory, unless ``--s3-endpoint-url`` names a real one such as MinIO) and the tracking server as real processes
on loopback ports, prints the tracking URI and runs until Ctrl-C. ``docker/compose.yaml`` runs the same
``mlflow server`` command (``mlflow_server_args``) against containers; ``tests/training/test_tracking_server.py``
runs a training job and the service against this stack.
"""

from __future__ import annotations

import logging
import os
import pwd
import shutil
import signal
import socket
import subprocess
import sys
import time
import urllib.error
import urllib.request
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path

import typer

log = logging.getLogger(__name__)

BUCKET = "wearmocap-mlflow"
DATABASE = "mlflow"
DB_USER = "wearmocap"
# moto accepts any key; a real store gets its own through the environment (AWS_ACCESS_KEY_ID, ...).
S3_TEST_CREDENTIALS = {
    "AWS_ACCESS_KEY_ID": "wearmocap",
    "AWS_SECRET_ACCESS_KEY": "wearmocap-secret",
    "AWS_DEFAULT_REGION": "us-east-1",
}
_NEW_OS_USER = "wearmocap-postgres"
# The project runs no jobs on the tracking server (MLflow's GenAI job runner: eight more processes per server).
MLFLOW_SERVER_ENV = {"MLFLOW_SERVER_ENABLE_JOB_EXECUTION": "false"}


class ServerError(RuntimeError):
    """A server of the stack did not start; the message names it and ends with its log."""


@dataclass
class Server:
    name: str
    proc: subprocess.Popen
    url: str
    log_path: Path
    stop_signal: int = signal.SIGTERM


@dataclass
class TrackingStack:
    tracking_uri: str
    backend_store_uri: str
    s3_endpoint_url: str
    bucket: str
    servers: list[Server] = field(default_factory=list)

    def s3_env(self) -> dict[str, str]:
        """What an S3 client (the tracking server, boto3) needs to reach the bucket."""
        keys = {k: os.environ.get(k, v) for k, v in S3_TEST_CREDENTIALS.items()}
        return {"MLFLOW_S3_ENDPOINT_URL": self.s3_endpoint_url, **keys}


def mlflow_server_args(backend_store_uri: str, bucket: str, host: str, port: int, workers: int = 1) -> list[str]:
    """``mlflow server`` with a database backend and S3 artifacts served through the server (the one command of
    the test stack and of ``docker/compose.yaml``); the S3 endpoint and keys come from the environment."""
    return [
        "server",
        "--backend-store-uri",
        backend_store_uri,
        "--artifacts-destination",
        f"s3://{bucket}/",
        "--host",
        host,
        "--port",
        str(port),
        "--workers",
        str(workers),
    ]


def find_postgres_bin() -> Path | None:
    """The folder with ``initdb`` and ``postgres``: $WEARMOCAP_POSTGRES_BIN, then the PATH, then the newest
    ``/usr/lib/postgresql/<major>/bin`` (where Debian's ``postgresql`` package puts them, off the PATH)."""
    candidates = [Path(p) for p in [os.environ.get("WEARMOCAP_POSTGRES_BIN")] if p]
    if initdb := shutil.which("initdb"):
        candidates.append(Path(initdb).resolve().parent)
    debian = Path("/usr/lib/postgresql").glob("*/bin")
    candidates += sorted(debian, key=lambda p: int(p.parent.name) if p.parent.name.isdigit() else -1, reverse=True)
    return next((c for c in candidates if (c / "initdb").is_file() and (c / "postgres").is_file()), None)


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _postgres_os_user() -> str | None:
    """PostgreSQL refuses to run as root: there, the ``postgres`` user of the distribution's package, or a system
    user made for it. ``None`` (the current user) otherwise."""
    if os.geteuid() != 0:
        return None
    for name in ("postgres", _NEW_OS_USER):
        try:
            pwd.getpwnam(name)
            return name
        except KeyError:
            continue
    subprocess.run(
        ["useradd", "--system", "--user-group", "--no-create-home", "--shell", "/usr/sbin/nologin", _NEW_OS_USER],
        check=True,
    )
    return _NEW_OS_USER


def _as_user(user: str | None) -> dict:
    """Popen arguments that run a command as ``user`` (no supplementary groups of the caller)."""
    if user is None:
        return {}
    entry = pwd.getpwnam(user)
    return {"user": entry.pw_uid, "group": entry.pw_gid, "extra_groups": []}


def _spawn(name: str, cmd: list[str], log_dir: Path, url: str, **popen) -> Server:
    log_path = log_dir / f"{name}.log"
    with open(log_path, "wb") as out:  # each server in its own process group: stopping it stops its workers
        proc = subprocess.Popen(cmd, stdout=out, stderr=subprocess.STDOUT, process_group=0, **popen)
    return Server(name, proc, url, log_path)


def _failed(server: Server, what: str) -> ServerError:
    tail = server.log_path.read_text(errors="replace")[-2000:] if server.log_path.exists() else ""
    return ServerError(f"{server.name}: {what} (log {server.log_path}):\n{tail}")


def _wait(server: Server, ready, timeout_s: float) -> None:
    """Poll ``ready()`` until it returns True; the server exiting or the deadline passing raise ServerError."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if server.proc.poll() is not None:
            raise _failed(server, f"exited with {server.proc.returncode} while starting")
        if ready():
            return
        time.sleep(0.2)
    raise _failed(server, f"not ready after {timeout_s:.0f} s")


def _http_ok(url: str, method: str = "GET") -> bool:
    try:
        with urllib.request.urlopen(urllib.request.Request(url, method=method), timeout=2) as response:
            return 200 <= response.status < 300
    except (urllib.error.URLError, OSError):
        return False


def stop(server: Server, timeout_s: float = 20) -> None:
    """Signal the server's process group; kill it if it has not ended within ``timeout_s``."""
    if server.proc.poll() is None:
        try:
            os.killpg(server.proc.pid, server.stop_signal)
            server.proc.wait(timeout=timeout_s)
        except subprocess.TimeoutExpired:
            os.killpg(server.proc.pid, signal.SIGKILL)
            server.proc.wait()
    try:  # workers left behind by a leader that ended first
        os.killpg(server.proc.pid, signal.SIGKILL)
    except ProcessLookupError:
        pass


def start_postgres(root: Path, log_dir: Path, durable: bool = True, timeout_s: float = 30) -> tuple[Server, str]:
    """A PostgreSQL cluster under ``root/postgres`` (created by initdb on first use) on a free loopback port, with a
    ``mlflow`` database; returns the server and the database URI. Loopback connections are trusted (no password):
    a server for this machine only. ``durable=False`` turns fsync off (tests)."""
    bin_dir = find_postgres_bin()
    if bin_dir is None:
        raise ServerError("PostgreSQL binaries (initdb, postgres) not found: install the postgresql package")
    user = _postgres_os_user()
    data = root / "postgres"
    if user is not None:  # the cluster belongs to the OS user that runs it
        root.mkdir(parents=True, exist_ok=True)
        shutil.chown(root, user)
    if not (data / "PG_VERSION").exists():
        initdb = [str(bin_dir / "initdb"), "-D", str(data), "-U", DB_USER, "--auth=trust", "-E", "UTF8", "--no-sync"]
        done = subprocess.run(initdb, cwd=root, capture_output=True, text=True, **_as_user(user))
        if done.returncode != 0:
            raise ServerError(f"initdb -D {data} failed ({done.returncode}): {done.stderr.strip()}")
    port = free_port()
    cmd = [str(bin_dir / "postgres"), "-D", str(data), "-h", "127.0.0.1", "-p", str(port), "-k", ""]
    if not durable:
        cmd += ["-c", "fsync=off", "-c", "synchronous_commit=off", "-c", "full_page_writes=off"]
    server = _spawn("postgres", cmd, log_dir, f"postgresql://{DB_USER}@127.0.0.1:{port}", cwd=root, **_as_user(user))
    server.stop_signal = signal.SIGINT  # fast shutdown: SIGTERM would wait for every client to leave
    try:
        _wait(server, lambda: _create_database(port), timeout_s)
    except ServerError:
        stop(server)
        raise
    return server, f"{server.url}/{DATABASE}".replace("postgresql://", "postgresql+psycopg2://", 1)


def _create_database(port: int) -> bool:
    """True once the server accepts connections and the ``mlflow`` database exists."""
    import psycopg2  # the driver MLflow's PostgreSQL store needs anyway

    try:
        conn = psycopg2.connect(host="127.0.0.1", port=port, user=DB_USER, dbname="postgres", connect_timeout=2)
    except psycopg2.OperationalError:
        return False
    try:
        conn.autocommit = True
        with conn.cursor() as cur:
            cur.execute("SELECT 1 FROM pg_database WHERE datname = %s", (DATABASE,))
            if cur.fetchone() is None:
                cur.execute(f"CREATE DATABASE {DATABASE}")
    finally:
        conn.close()
    return True


def start_s3(log_dir: Path, bucket: str = BUCKET, timeout_s: float = 30) -> Server:
    """moto's S3 server (objects in memory, gone when it stops) on a free loopback port, with ``bucket``."""
    port = free_port()
    cmd = [sys.executable, "-m", "moto.server", "-H", "127.0.0.1", "-p", str(port)]
    server = _spawn("s3", cmd, log_dir, f"http://127.0.0.1:{port}")
    try:
        _wait(server, lambda: _http_ok(f"{server.url}/"), timeout_s)
        if not _http_ok(f"{server.url}/{bucket}", "PUT"):  # CreateBucket; moto does not check signatures
            raise _failed(server, f"could not create bucket {bucket}")
    except ServerError:
        stop(server)
        raise
    return server


def start_mlflow(stack: TrackingStack, log_dir: Path, port: int | None = None, timeout_s: float = 90) -> Server:
    """``mlflow server`` on the stack's database and bucket; ready once ``/health`` answers (after the schema
    migrations of a new database)."""
    port = port or free_port()
    cmd = [
        sys.executable,
        "-m",
        "mlflow",
        *mlflow_server_args(stack.backend_store_uri, stack.bucket, "127.0.0.1", port),
    ]
    server = _spawn(
        "mlflow", cmd, log_dir, f"http://127.0.0.1:{port}", env={**os.environ, **MLFLOW_SERVER_ENV, **stack.s3_env()}
    )
    try:
        _wait(server, lambda: _http_ok(f"{server.url}/health"), timeout_s)
    except ServerError:
        stop(server)
        raise
    return server


@contextmanager
def tracking_stack(
    root: Path, port: int | None = None, s3_endpoint_url: str | None = None, durable: bool = True
) -> Iterator[TrackingStack]:
    """Start PostgreSQL, the S3 store (moto, unless ``s3_endpoint_url`` is given and holds ``BUCKET``) and the
    tracking server under ``root``; stops every one of them on leaving, also on errors. As root, ``root`` must be
    reachable by the OS user that runs PostgreSQL."""
    log_dir = root / "logs"
    log_dir.mkdir(parents=True, exist_ok=True)
    servers: list[Server] = []
    try:
        pg, backend = start_postgres(root, log_dir, durable)
        servers.append(pg)
        if s3_endpoint_url is None:
            servers.append(start_s3(log_dir))
            s3_endpoint_url = servers[-1].url
        stack = TrackingStack("", backend, s3_endpoint_url, BUCKET, servers)
        servers.append(start_mlflow(stack, log_dir, port))
        stack.tracking_uri = servers[-1].url
        yield stack
    finally:
        for server in reversed(servers):
            stop(server)


def main(
    root: Path = typer.Option(Path(".cache/team-tracking"), help="PostgreSQL cluster and server logs"),
    port: int = typer.Option(5000, help="tracking server port (loopback)"),
    s3_endpoint_url: str | None = typer.Option(
        None, help="an S3 store that holds the bucket (MinIO, ...); default: start moto's server (in memory)"
    ),
) -> None:
    """Run the team tracking server until Ctrl-C; training jobs log to it with MLFLOW_TRACKING_URI."""
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    for signum in (signal.SIGINT, signal.SIGTERM):  # `kill` stops the servers as Ctrl-C does (also in background)
        signal.signal(signum, _interrupt)
    with tracking_stack(root.resolve(), port, s3_endpoint_url) as stack:
        log.info("database %s, artifacts s3://%s/ at %s", stack.backend_store_uri, stack.bucket, stack.s3_endpoint_url)
        log.info("tracking server: export MLFLOW_TRACKING_URI=%s", stack.tracking_uri)
        try:
            while all(s.proc.poll() is None for s in stack.servers):
                time.sleep(1)
            ended = [s.name for s in stack.servers if s.proc.poll() is not None]
            raise ServerError(f"{', '.join(ended)} ended; stopping the others (logs in {root / 'logs'})")
        except KeyboardInterrupt:
            log.info("stopping")


def _interrupt(signum: int, frame: object) -> None:
    raise KeyboardInterrupt


if __name__ == "__main__":
    typer.run(main)
