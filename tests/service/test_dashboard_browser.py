"""The live view in a real headless Chromium against a real uvicorn server with the shipped models: the page plays
its bundled recording through ``/v1/stream`` at real time until it shows the recording's own placement of all seven
sensors, with the pose figure and the knee chart (sleeves and pose) drawn; behind an API key, the key field unlocks
the models and the streams (a browser sends it as a WebSocket subprotocol).

Needs Debian's ``chromium`` and ``chromium-driver`` (``/usr/bin/chromium``, ``/usr/bin/chromedriver``) and selenium.
"""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from benchmarks.servers import REPO, start_service, stop
from service.core.manifest import read_manifest
from service.inference.registry import version_key
from tests.service.conftest import write_tiny_model

CHROMIUM, CHROMEDRIVER = Path("/usr/bin/chromium"), Path("/usr/bin/chromedriver")
FLAGS = (
    "--headless --no-sandbox --disable-gpu --disable-quic --no-first-run --disable-background-networking "
    "--disable-component-update --disable-sync --window-size=1500,1250"
)
RECORDING = json.loads((REPO / "service" / "static" / "dashboard" / "recording.json").read_text())

pytestmark = pytest.mark.skipif(
    not CHROMIUM.exists(), reason="no /usr/bin/chromium (apt-get install chromium chromium-driver)"
)


@pytest.fixture(scope="module")
def browser(tmp_path_factory: pytest.TempPathFactory):
    from selenium import webdriver
    from selenium.webdriver.chrome.service import Service

    options = webdriver.ChromeOptions()
    options.binary_location = str(CHROMIUM)
    for flag in [*FLAGS.split(), f"--user-data-dir={tmp_path_factory.mktemp('chromium')}"]:
        options.add_argument(flag)
    driver = webdriver.Chrome(service=Service(str(CHROMEDRIVER)), options=options)
    yield driver
    driver.quit()


@pytest.fixture(scope="module")
def server():
    proc, base = start_service(REPO / "onnx_models", threads=1)
    yield base
    stop(proc)


def _wait(driver, seconds: float, condition, message: str):
    from selenium.webdriver.support.ui import WebDriverWait

    return WebDriverWait(driver, seconds, poll_frequency=0.2).until(lambda d: condition(d), message)


def _served(name: str) -> Path:
    """The version the service serves by default: the newest under onnx_models/<name>."""
    return max((REPO / "onnx_models" / name).iterdir(), key=lambda d: version_key(d.name))


def _cells(driver, field: str) -> dict[str, str]:
    rows = driver.find_elements("css selector", "#sensors tbody tr")
    return {
        r.get_attribute("data-sensor"): r.find_element("css selector", f'[data-field="{field}"]').text for r in rows
    }


def test_the_page_streams_its_recording_and_shows_the_right_assignment_and_pose(browser, server: str) -> None:
    browser.get(f"{server}/dashboard")
    _wait(browser, 10, lambda d: d.find_element("id", "play").is_enabled(), "the models never loaded")
    run_links = [a.get_attribute("href") for a in browser.find_elements("css selector", "#models a")]
    assert "http://127.0.0.1:5000/#/models/i2s_assignment" in run_links, run_links
    assert browser.find_element("css selector", '#models tr[data-model="pose_lower3_stream"]')
    labels = {s["sensor_id"]: s["segment"] for s in RECORDING["imu"]["sensors"]}
    # the page names every served model that trained on its recording (then the view is no held-out figure)
    source, trial = RECORDING["name"].split("/")
    for name in ("i2s_assignment", "flex_capacitive_knee"):
        manifest = read_manifest(_served(name) / "manifest.json")
        data = manifest.training_data
        trials = data.get("train_trials") or [data.get("train_trial")]
        seen = RECORDING["name"] in data.get("real_train_recordings", []) or (
            source in data.get("sources", []) and trial in trials
        )
        named = f"{name} {manifest.version}" in browser.find_element("id", "recording").text
        assert named == seen, (name, manifest.version, seen)

    browser.find_element("id", "play").click()  # at real time: the first windows are full after 128 samples (2.1 s)
    _wait(browser, 15, lambda d: _cells(d, "segment") == labels, f"never showed {labels}")
    assert all(int(n) > 0 for n in _cells(browser, "windows").values())
    assert all(0.0 < float(p) <= 1.0 for p in _cells(browser, "p_correct").values())
    assert set(_cells(browser, "committed").values()) <= {"yes", "no"}  # each sensor on its own
    assert browser.find_element("id", "status").text in ("assigned", "not_enough_walking")
    served = _served("i2s_assignment")
    if read_manifest(served / "manifest.json").confidence.session is not None:  # the whole assignment's probability
        assert 0.0 <= float(browser.find_element("id", "p-all").text) <= 1.0
    else:  # calibrated per sensor only: no probability of the whole answer to show
        assert not browser.find_element("id", "p-all-wrap").is_displayed()

    figure = browser.find_element("id", "figure")
    _wait(browser, 10, lambda d: int(figure.get_attribute("data-frames")) > 0, "no pose frame drawn")
    assert figure.is_displayed() and figure.size["width"] > 300
    assert "calibrated by the assignment" in browser.find_element("id", "pose-note").text
    assert browser.execute_script("return !!arguments[0].getContext('webgl2')", figure)  # three.js draws in WebGL
    chart = browser.find_element("id", "flex-chart")
    assert chart.is_displayed()
    assert "flex_capacitive_knee" in browser.find_element("id", "flex-note").text
    # both knees twice: from the sleeves (the flex stream) and from the IMU pose's joint angles (the pose stream)
    knees = {f"{side} knee, {by}" for side in ("Left", "Right") for by in ("sleeve", "IMU pose")}
    series = lambda d: set((chart.get_attribute("data-series") or "").split("|"))  # noqa: E731
    _wait(browser, 10, lambda d: series(d) == knees, f"the chart never drew {knees}")

    browser.find_element("id", "stop").click()
    _wait(browser, 10, lambda d: d.find_element("tag name", "body").get_attribute("data-state") == "done", "not done")
    assert browser.find_element("id", "log").text == ""  # every stream closed with 1000, no error message


def test_behind_an_api_key_the_key_field_unlocks_the_models_and_the_stream(browser, tmp_path: Path) -> None:
    models = tmp_path / "onnx_models"
    write_tiny_model(models, "i2s_assignment")
    write_tiny_model(models, "i2s_alignment")
    proc, base = start_service(models, threads=1, api_key="secret", capacity_windows_per_s="1000")
    try:
        browser.get(f"{base}/dashboard?speed=4")
        note = browser.find_element("id", "models-note")
        _wait(browser, 10, lambda d: "asks for its API key" in note.text, "no word about the key")
        assert not browser.find_element("id", "play").is_enabled()
        browser.find_element("id", "key").send_keys("secret")
        browser.find_element("css selector", "#key-form button").click()
        _wait(browser, 10, lambda d: d.find_elements("css selector", '#models tr[data-model="i2s_assignment"]'), "")
        assert browser.find_element("id", "play").is_enabled()
        # a browser's WebSocket carries no X-API-Key header: the key goes as the subprotocol wearmocap.key.<base64url>
        browser.find_element("id", "play").click()
        _wait(browser, 20, lambda d: all(v != "–" for v in _cells(d, "segment").values()), "no assignment came")
        assert "1008" not in browser.find_element("id", "log").text
    finally:
        stop(proc)
