"""Start and stop the servers the benchmarks compare (real processes on loopback ports)."""

from __future__ import annotations

import os
import shutil
import socket
import subprocess
import sys
import time
from pathlib import Path

import httpx

from service.inference.registry import newest_version_dir

REPO = Path(__file__).resolve().parents[1]
LOGS = REPO / "artifacts" / "logs"


def served_dir(name: str) -> Path:
    """The version of ``name`` the service serves by default: the newest under onnx_models/."""
    newest = newest_version_dir(REPO / "onnx_models", name)
    if newest is None:
        raise SystemExit(f"no shipped {name} under onnx_models/")
    return newest


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def wait_ready(url: str, proc: subprocess.Popen, timeout_s: float = 120) -> None:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if proc.poll() is not None:
            raise RuntimeError(f"server exited with {proc.returncode}")
        try:
            if httpx.get(url, timeout=1).status_code == 200:
                return
        except httpx.HTTPError:
            pass
        time.sleep(0.3)
    raise RuntimeError(f"{url} not ready in {timeout_s} s")


def start_process(
    cmd: list[str], ready_path: str, port: int, env: dict[str, str] | None = None, timeout_s: float = 120
) -> tuple[subprocess.Popen, str]:
    """Start a server on ``port`` and wait until ``ready_path`` answers 200; returns (process, base URL).

    Its output goes to ``artifacts/logs/server-<port>.log``, so a benchmark's server errors can be read.
    """
    LOGS.mkdir(parents=True, exist_ok=True)
    with open(LOGS / f"server-{port}.log", "wb") as log:
        proc = subprocess.Popen(cmd, cwd=REPO, env={**os.environ, **(env or {})}, stdout=log, stderr=subprocess.STDOUT)
    base = f"http://127.0.0.1:{port}"
    try:
        wait_ready(f"{base}{ready_path}", proc, timeout_s)
    except RuntimeError:
        stop(proc)
        raise
    return proc, base


def server_log(base: str) -> Path:
    """The log file of the server started at ``base`` by ``start_process``."""
    return LOGS / f"server-{base.rsplit(':', 1)[1]}.log"


def process_cpu_s(pid: int, main_thread: bool = False) -> float | None:
    """CPU seconds (user + system) a process has used, all its threads or its main thread only (a Python server's
    event loop); None where ``/proc`` is not there."""
    path = f"/proc/{pid}/task/{pid}/stat" if main_thread else f"/proc/{pid}/stat"
    try:
        fields = Path(path).read_text().rsplit(")", 1)[1].split()
    except OSError:
        return None
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")  # utime, stime (fields 14, 15)


def start_service(models_dir: Path, threads: int = 2, **env: str) -> tuple[subprocess.Popen, str]:
    """``python -m service`` on the models under ``models_dir``; extra settings as WEARMOCAP_* values."""
    port = free_port()
    settings = {"WEARMOCAP_MODELS_DIR": str(models_dir), "WEARMOCAP_INFERENCE_THREADS": str(threads)}
    settings.update({f"WEARMOCAP_{k.upper()}": v for k, v in env.items()})
    return start_process([sys.executable, "-m", "service", "--port", str(port)], "/ready", port, settings)


def start_mlflow_serve(model_dir: Path) -> tuple[subprocess.Popen, str]:
    """``mlflow models serve`` on an MLflow model directory, with the current environment."""
    port = free_port()
    mlflow_bin = shutil.which("mlflow") or str(Path(sys.executable).parent / "mlflow")
    cmd = [mlflow_bin, "models", "serve", "-m", str(model_dir), "-p", str(port), "--env-manager", "local", "-w", "1"]
    return start_process(cmd, "/ping", port)


def start_mlflow_server(root: Path) -> tuple[subprocess.Popen, str]:
    """A real MLflow tracking server with a sqlite store and an artifact root under ``root``."""
    port = free_port()
    cmd = [
        sys.executable,
        "-m",
        "mlflow",
        "server",
        "--backend-store-uri",
        f"sqlite:///{root / 'mlflow.db'}",
        "--artifacts-destination",
        str(root / "artifacts"),
        "--host",
        "127.0.0.1",
        "--port",
        str(port),
        "--workers",
        "1",
    ]
    return start_process(cmd, "/health", port)


def stop(proc: subprocess.Popen) -> None:
    proc.terminate()
    try:
        proc.wait(timeout=20)
    except subprocess.TimeoutExpired:
        proc.kill()
