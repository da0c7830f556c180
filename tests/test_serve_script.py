"""``scripts/serve.sh``, the README's main command: SIGTERM stops the service, the MLflow UI and every process they
started; a port in use is named before anything starts."""

from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import httpx

from benchmarks.servers import REPO, free_port


def _listening(port: int) -> bool:
    with socket.socket() as s:
        return s.connect_ex(("127.0.0.1", port)) == 0


def _wait(condition, timeout_s: float) -> bool:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if condition():
            return True
        time.sleep(0.5)
    return False


def test_sigterm_stops_the_service_the_ui_and_their_children(tmp_path: Path) -> None:
    port, ui_port = free_port(), free_port()
    store = f"sqlite:///{tmp_path / 'mlflow.db'}"
    env = {**os.environ, "PORT": str(port), "MLFLOW_PORT": str(ui_port), "MLFLOW_TRACKING_URI": store}
    # A store with a run already: the UI starts without restoring the snapshot (a minute here; tests/training/
    # test_snapshot.py tests the restore).
    one_run = "import mlflow; mlflow.set_experiment('serve-test'); mlflow.start_run(); mlflow.end_run()"
    subprocess.run([sys.executable, "-c", one_run], env=env, cwd=tmp_path, check=True, capture_output=True)
    log = open(tmp_path / "serve.log", "wb")
    proc = subprocess.Popen(["bash", "scripts/serve.sh"], cwd=REPO, env=env, stdout=log, stderr=subprocess.STDOUT)
    try:
        ready = lambda: _listening(port) and httpx.get(f"http://127.0.0.1:{port}/ready", timeout=2).status_code == 200  # noqa: E731
        assert _wait(ready, 180), (tmp_path / "serve.log").read_text()[-2000:]
        assert _wait(lambda: _listening(ui_port), 240), (tmp_path / "serve.log").read_text()[-2000:]
        proc.send_signal(signal.SIGTERM)
        assert proc.wait(timeout=30) == 143
        assert _wait(lambda: not _listening(port) and not _listening(ui_port), 20), "a server outlived serve.sh"
    finally:
        if proc.poll() is None:
            proc.kill()
        log.close()


def test_a_port_in_use_is_named_before_anything_starts() -> None:
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        port = taken.getsockname()[1]
        env = {**os.environ, "PORT": str(port), "MLFLOW_PORT": str(free_port())}
        out = subprocess.run(
            ["bash", "scripts/serve.sh"], cwd=REPO, env=env, capture_output=True, text=True, timeout=60
        )
    assert out.returncode == 1
    assert f"port {port} on 127.0.0.1 is in use" in out.stderr and "set PORT or MLFLOW_PORT" in out.stderr
