"""The web page's strip of parts, in headless Chromium against a real `dgs serve`: a sequence of
three groups of pictures (submitted with the Python client) shows one cell per group, each
running with its percentage and then done (naming the worker that ran it), and the job
succeeds; no console errors.

Needs Debian's chromium and chromium-driver, as tests/e2e/test_web.py."""

from __future__ import annotations

import shutil
from pathlib import Path

import pytest

from live_server import ROOT, LiveServer, create_key

CHROMIUM = shutil.which("chromium") or "/usr/bin/chromium"
CHROMEDRIVER = shutil.which("chromedriver") or "/usr/bin/chromedriver"
SHOTS = ROOT / "test-artifacts" / "browser"
CONFIG = {"train": {"schedule": {"iterations": 200, "stage2_start": 60, "stage3_start": 140,
                                 "densify_from": 10, "densify_until": 120,
                                 "densify_interval": 20, "reset_interval": 80,
                                 "sh_interval": 20}, "init_points": 300},
          "sequence": {"num_nodes": 32}, "mesh": {"enabled": False}}

pytestmark = pytest.mark.timeout(420)

selenium = pytest.importorskip("selenium", reason="selenium is in the dev extra: "
                               "pip install -e '.[dev]'")
if not (Path(CHROMIUM).exists() and Path(CHROMEDRIVER).exists()):
    pytest.skip("browser tests need Chromium: apt-get install -y chromium chromium-driver",
                allow_module_level=True)

from selenium import webdriver  # noqa: E402
from selenium.webdriver.chrome.service import Service  # noqa: E402
from selenium.webdriver.common.by import By  # noqa: E402
from selenium.webdriver.support.ui import Select, WebDriverWait  # noqa: E402


def _until(driver, what: str, predicate, timeout: float = 120):
    try:
        return WebDriverWait(driver, timeout, poll_frequency=0.2).until(predicate)
    except Exception:
        SHOTS.mkdir(parents=True, exist_ok=True)
        driver.save_screenshot(str(SHOTS / "failed-parts.png"))
        raise AssertionError(f"timed out waiting for {what}; job-status: "
                             f"{driver.find_element(By.ID, 'job-status').text}; console: "
                             f"{driver.get_log('browser')}") from None


def _cells(driver) -> list[tuple[str, str]]:
    """(class, text) of each cell, read in one script: the strip is redrawn on every event, so
    elements found one call earlier may be gone."""
    return [tuple(c) for c in driver.execute_script(
        "return [...document.querySelectorAll('#job-parts .part')]"
        ".map((c) => [c.className, c.textContent]);")]


def test_the_page_shows_a_strip_of_parts(tmp_path):
    from core.synth import SynthConfig, synthesize
    from service.client import Client

    data = tmp_path / "data"
    key = create_key(data, "studio")
    server = LiveServer(data, tmp_path / "serve.log").start()
    opts = webdriver.ChromeOptions()
    opts.binary_location = CHROMIUM
    for arg in ("--headless", "--no-sandbox", "--disable-gpu", "--window-size=1280,1600"):
        opts.add_argument(arg)
    opts.set_capability("goog:loggingPrefs", {"browser": "ALL"})
    driver = webdriver.Chrome(service=Service(CHROMEDRIVER), options=opts)
    try:
        server.wait_worker()
        synthesize(tmp_path / "capture", SynthConfig(frames=6, views=8, width=32, height=32,
                                                     seed=4, ao_directions=8))
        with Client(server.url, key) as client:
            cap = client.create_capture(tmp_path / "capture")
            client.upload_capture(cap["id"], tmp_path / "capture")
            assert client.commit(cap["id"], timeout=120)["state"] == "ready"
            job = client.submit(cap["id"], {"preset": "test", "gop": 2, "config": CONFIG})
        assert len(job["parts"]) == 3

        driver.get(server.url + "/")
        _until(driver, "sign-in", lambda d: d.find_element(By.ID, "signin").is_displayed())
        driver.find_element(By.ID, "api-key").send_keys(key)
        driver.find_element(By.ID, "signin-button").click()
        _until(driver, "the workspace",
               lambda d: d.find_element(By.ID, "workspace").is_displayed())
        _until(driver, "the job in the list", lambda d: job["id"] in d.find_element(
            By.ID, "job-select").text)
        Select(driver.find_element(By.ID, "job-select")).select_by_value(job["id"])
        _until(driver, "a cell per part", lambda d: len(_cells(d)) == 3)
        _until(driver, "the job to end", lambda d: d.find_element(By.ID, "job-status")
               .get_attribute("data-state") in ("succeeded", "failed", "error"), 300)
        SHOTS.mkdir(parents=True, exist_ok=True)
        driver.save_screenshot(str(SHOTS / "parts-done.png"))
        assert "succeeded" in driver.find_element(By.ID, "job-status").text
        assert _cells(driver) == [("part part-succeeded", "✓")] * 3
        # A finished part still names the worker that ran it (issue 32).
        workers = driver.execute_script(
            "return [...document.querySelectorAll('#job-parts .part')]"
            ".map((c) => [c.dataset.worker, c.title]);")
        assert all(w and f" on {w}" in title for w, title in workers), workers
        errors = [e for e in driver.get_log("browser") if e["level"] == "SEVERE"]
        assert not errors, errors
    finally:
        driver.quit()
        server.stop()
