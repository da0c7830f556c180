"""Screenshots for the docs, taken in a headless Chromium (Debian's ``chromium`` and ``chromium-driver``, selenium):
the landing page ``/``, the live view ``/dashboard`` while it streams its recording, and the MLflow UI's page of
one experiment. The script starts the service (shipped models) and the MLflow UI (``training.cli ui``, on
./mlflow.db) itself and stops them at the end.

    .venv/bin/python scripts/screenshots.py                 # docs/img/landing.png, dashboard.png, mlflow_experiment.png
    .venv/bin/python scripts/screenshots.py --no-mlflow     # the service's two pages only
    .venv/bin/python scripts/screenshots.py --fresh-store   # the MLflow UI as a fresh clone shows it
"""

from __future__ import annotations

import argparse
import os
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from benchmarks.servers import free_port, start_service, stop, wait_ready  # noqa: E402

OUT = REPO / "docs" / "img"
FLAGS = (
    "--headless --no-sandbox --disable-gpu --disable-quic --no-first-run --disable-background-networking "
    "--disable-component-update --disable-sync --hide-scrollbars"
)


def chromium(user_data_dir: str):
    from selenium import webdriver
    from selenium.webdriver.chrome.service import Service

    options = webdriver.ChromeOptions()
    options.binary_location = "/usr/bin/chromium"
    for flag in [*FLAGS.split(), f"--user-data-dir={user_data_dir}"]:
        options.add_argument(flag)
    return webdriver.Chrome(service=Service("/usr/bin/chromedriver"), options=options)


def wait_for(condition, seconds: float, what: str) -> None:
    deadline = time.monotonic() + seconds
    while not condition():
        if time.monotonic() > deadline:
            raise TimeoutError(f"{what}: not seen within {seconds:g} s")
        time.sleep(0.2)


def service_pages(driver, base: str, stream_s: float) -> None:
    driver.set_window_size(1100, 680)
    driver.get(f"{base}/")
    driver.save_screenshot(str(OUT / "landing.png"))
    driver.set_window_size(1500, 1160)
    driver.get(f"{base}/dashboard")
    wait_for(lambda: driver.find_element("id", "play").is_enabled(), 15, "the models in the live view")
    driver.find_element("id", "play").click()
    time.sleep(stream_s)  # real time: the chart shows the last 10 s
    driver.save_screenshot(str(OUT / "dashboard.png"))
    driver.find_element("id", "stop").click()


def mlflow_page(driver, experiment_id: str, store: str | None) -> None:
    port = free_port()
    cmd = [sys.executable, "-m", "training.cli", "ui", "--port", str(port)]
    env = {**os.environ, "MLFLOW_TRACKING_URI": store} if store else None
    # its own process group: training.cli ui runs ``mlflow ui`` as a child, which is stopped with it
    proc = subprocess.Popen(
        cmd, cwd=REPO, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.STDOUT, process_group=0
    )
    base = f"http://127.0.0.1:{port}"
    try:
        wait_ready(f"{base}/health", proc, 180)
        driver.set_window_size(1500, 900)
        driver.get(f"{base}/#/experiments/{experiment_id}/runs")
        wait_for(lambda: driver.find_elements("css selector", "[role=row]"), 60, "the runs table")
        time.sleep(5)  # the assistant panel opens late
        for button in driver.find_elements("css selector", "button[aria-label=Close]"):  # the assistant panel
            button.click()
        for toggle in driver.find_elements("xpath", "//*[normalize-space(text())='Model training']")[:1]:
            toggle.click()  # the sidebar of training runs rather than GenAI's
        time.sleep(1)
        wait_for(lambda: driver.find_elements("css selector", "a[href*='/runs/']"), 60, "the runs' links")
        time.sleep(2)
        driver.save_screenshot(str(OUT / "mlflow_experiment.png"))
    finally:
        os.killpg(proc.pid, signal.SIGTERM)
        proc.wait(timeout=30)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--stream-s", type=float, default=13.0, help="how long the live view streams before its shot")
    parser.add_argument("--experiment-id", default="1", help="the MLflow experiment to show (1: i2s)")
    parser.add_argument("--no-mlflow", action="store_true", help="skip the MLflow UI")
    parser.add_argument(
        "--fresh-store", action="store_true", help="the UI on a new store, as a fresh clone's (the snapshot restored)"
    )
    args = parser.parse_args()
    OUT.mkdir(parents=True, exist_ok=True)
    proc, base = start_service(REPO / "onnx_models", threads=1)
    driver = chromium(tempfile.mkdtemp(prefix="chromium-"))
    try:
        service_pages(driver, base, args.stream_s)
        if not args.no_mlflow:
            store = f"sqlite:///{tempfile.mkdtemp(prefix='mlflow-')}/mlflow.db" if args.fresh_store else None
            mlflow_page(driver, args.experiment_id, store)
    finally:
        driver.quit()
        stop(proc)
    print(f"screenshots in {OUT}")


if __name__ == "__main__":
    main()
