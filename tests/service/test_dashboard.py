"""The live view's page and assets (``service.api.dashboard``, ``service/static/dashboard``): served from the package
with the right content types, every module a page script imports is there, the bundled recording matches what its
script writes from the data directory. The page in a real browser: ``test_dashboard_browser.py``."""

from __future__ import annotations

import importlib.util
import json
import re
from pathlib import Path

import numpy as np
import pytest
from fastapi.testclient import TestClient

from service.app import create_app
from service.core.body import BODY_SEGMENTS, PARENT_INDEX
from service.core.segments import SEGMENTS
from service.settings import Settings

REPO = Path(__file__).resolve().parents[2]
STATIC = REPO / "service" / "static" / "dashboard"
IMPORT = re.compile(r"""(?:\bfrom\s*|\bimport\s*\(\s*)["'](\./[^"']+)["']""")
TYPES = {".js": "javascript", ".css": "text/css", ".json": "application/json", ".bin": "application/octet-stream"}


@pytest.fixture
def keyed(tiny_models: Path):
    with TestClient(
        create_app(Settings(models_dir=tiny_models, api_key="k", ui_url="http://mlflow.example:5000/"))
    ) as c:
        yield c


def _assets(client: TestClient) -> set[str]:
    """Every URL the page loads: its links and scripts, and what each script imports, followed to the end."""
    page = client.get("/dashboard").text
    todo = [u for u in re.findall(r"""(?:src|href)=["'](/static/[^"']+)["']""", page)]
    todo += ["/static/dashboard/recording.json", "/static/dashboard/recording.bin"]  # fetched by player.js
    seen: set[str] = set()
    while todo:
        url = todo.pop()
        if url in seen:
            continue
        seen.add(url)
        if url.endswith(".js"):
            base = url.rsplit("/", 1)[0]
            todo += [f"{base}/{m.removeprefix('./')}" for m in IMPORT.findall(client.get(url).text)]
    return seen


def test_the_page_and_every_asset_are_served_with_their_content_types(client: TestClient) -> None:
    page = client.get("/dashboard")
    assert page.status_code == 200 and page.headers["content-type"].startswith("text/html")
    assert "https://" not in page.text and "cdn" not in page.text.lower()  # works with no network
    assets = _assets(client)
    expected = {"main.js", "player.js", "figure.js", "chart.js", "models.js", "dom.js", "dashboard.css"}
    assert {f"/static/dashboard/{name}" for name in expected} <= assets
    assert {"/static/dashboard/vendor/three.module.min.js", "/static/dashboard/vendor/three.core.min.js"} <= assets
    for url in assets:
        r = client.get(url)
        assert r.status_code == 200 and len(r.content) > 100, url
        assert TYPES[Path(url).suffix] in r.headers["content-type"], (url, r.headers["content-type"])
    assert (STATIC / "vendor" / "three.LICENSE").read_text().startswith("The MIT License")
    assert "MIT License" in (STATIC / "recording.LICENSE").read_text()


def test_the_landing_page_links_the_dashboard(client: TestClient) -> None:
    assert 'href="/dashboard"' in client.get("/").text


def test_the_config_gives_the_mlflow_ui_the_key_rule_and_the_body_tree(client: TestClient, keyed: TestClient) -> None:
    config = client.get("/dashboard/config.json").json()
    assert config["ui_url"] == "http://127.0.0.1:5000" and config["key_required"] is False
    assert config["body"] == {"segments": list(BODY_SEGMENTS), "parents": list(PARENT_INDEX)}
    behind_key = keyed.get("/dashboard/config.json").json()  # the page and its config are not behind the key
    assert behind_key["ui_url"] == "http://mlflow.example:5000" and behind_key["key_required"] is True
    assert keyed.get("/dashboard").status_code == 200
    assert keyed.get("/v1/models").status_code == 401  # what the page's key field is for
    assert "i2s_assignment" in keyed.get("/v1/models", headers={"X-API-Key": "k"}).json()


def test_the_bundled_recording_is_what_its_script_writes(data_dir: Path, tmp_path: Path) -> None:
    meta = json.loads((STATIC / "recording.json").read_text())
    assert sorted(s["segment"] for s in meta["imu"]["sensors"]) == sorted(SEGMENTS)  # labels the page checks
    imu, flex = meta["imu"], meta["flex"]
    size = len(imu["sensors"]) * imu["frames"] * len(imu["values"]) + 2 * flex["readings"] * len(flex["channels"])
    values = np.fromfile(STATIC / "recording.bin", "<f4")
    assert values.size == size and np.isfinite(values).all()
    assert 20 <= imu["frames"] / imu["sample_rate_hz"] <= 30
    q = values[: len(imu["sensors"]) * imu["frames"] * 10].reshape(-1, 10)[:, 6:]
    np.testing.assert_allclose(np.linalg.norm(q, axis=1), 1.0, atol=1e-5)  # a pose stream refuses others
    spec = importlib.util.spec_from_file_location("dashboard_recording", REPO / "scripts" / "dashboard_recording.py")
    script = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(script)
    script.write_recording(data_dir, meta["start_s"], meta["seconds"], tmp_path)
    assert (tmp_path / "recording.bin").read_bytes() == (STATIC / "recording.bin").read_bytes()
    assert json.loads((tmp_path / "recording.json").read_text()) == meta
