"""The operator's web page in a real headless Chromium (Debian chromium + chromium-driver,
driven by selenium; nothing is downloaded at run time).

With an API token set: the page takes the token, opens a session on the simulated rig,
captures a pose with the suggested screen placement and shows the progress from the SSE
stream until it succeeds, cancels a second capture, calibrates, and opens the report.
Screenshots are saved under test-artifacts/web/ (ignored by git) and checked: not blank,
the key elements present.
"""

from __future__ import annotations

import os
import shutil
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from api.client import PhasecalClient
from api.config import ServiceConfig
from api.inprocess import running_service
from tests.api.test_api_session import screen_poses, small_rig

CHROMIUM, DRIVER = "/usr/bin/chromium", "/usr/bin/chromedriver"
TOKEN = "page-test-token"
ARTIFACTS = Path(__file__).resolve().parents[2] / "test-artifacts" / "web"


@pytest.fixture
def browser(tmp_path: Path):
    if not (os.path.exists(CHROMIUM) and os.path.exists(DRIVER)):
        msg = "chromium and chromium-driver (Debian) are needed: scripts/install-system-deps.sh"
        if os.environ.get("CI"):
            pytest.fail(msg)
        pytest.skip(msg)
    from selenium import webdriver
    from selenium.webdriver.chrome.service import Service

    opts = webdriver.ChromeOptions()
    opts.binary_location = CHROMIUM
    opts.page_load_strategy = "eager"  # do not wait for never-ending MJPEG previews
    for flag in ("--headless", "--no-sandbox", "--disable-gpu", "--disable-background-networking",
                 "--disable-component-update", "--no-first-run", "--window-size=1280,1800",
                 f"--user-data-dir={tmp_path / 'chromium-profile'}"):
        opts.add_argument(flag)
    driver = webdriver.Chrome(service=Service(executable_path=DRIVER), options=opts)
    driver.set_page_load_timeout(60)
    yield driver
    driver.quit()


def _shot(driver, name: str) -> np.ndarray:
    ARTIFACTS.mkdir(parents=True, exist_ok=True)
    path = ARTIFACTS / f"{name}.png"
    driver.save_screenshot(str(path))
    img = np.asarray(Image.open(path).convert("L"), dtype=np.float64)
    assert img.std() > 20, f"{path} looks blank"
    return img


def _wait(driver, condition, timeout: float = 180.0):
    from selenium.webdriver.support.ui import WebDriverWait

    return WebDriverWait(driver, timeout, poll_frequency=0.2).until(condition)


def _loaded(driver, css: str) -> bool:
    return bool(driver.execute_script(
        "const i = document.querySelector(arguments[0]);"
        "return !!i && !i.hidden && i.complete && i.naturalWidth > 0;", css))


def test_page_capture_progress_calibrate_report(browser, tmp_path: Path) -> None:
    from selenium.webdriver.common.by import By
    from selenium.webdriver.support.ui import Select

    if ARTIFACTS.exists():
        shutil.rmtree(ARTIFACTS)
    with running_service(ServiceConfig(data_dir=tmp_path / "data", token=TOKEN)) as (url, _):
        api = PhasecalClient(url, token=TOKEN)
        # wall-clock pacing: on virtual time a 38-frame capture ends in a fraction of a
        # second, before the page could show the bar moving
        rig = api.post("/rigs", {"name": "sim-small", "config": {**small_rig(), "clock": "real"}})
        d = browser
        d.get(url + "/")
        d.find_element(By.ID, "token").send_keys(TOKEN)
        d.find_element(By.CSS_SELECTOR, "#token-form button").click()
        _wait(d, lambda d: d.find_element(By.ID, "status").text == "ready")
        Select(d.find_element(By.ID, "new-session-rig")).select_by_value(rig["id"])
        d.find_element(By.CSS_SELECTOR, "#new-session button").click()
        _wait(d, lambda d: d.find_element(By.ID, "session-title").text.startswith("Session"))
        sid = _wait(d, lambda d: d.find_element(By.CSS_SELECTOR, "#sessions li.current")
                    ).get_attribute("data-session")
        # Three varied poses from a rig script, so that guidance and a fit have data.
        for pose in screen_poses(3, seed=11):
            job = api.wait(api.post(f"/sessions/{sid}/poses", {"screen_pose": pose}))
            assert job["status"] == "succeeded", job
        d.refresh()
        _wait(d, lambda d: d.find_element(By.ID, "status").text == "ready")
        d.find_element(By.CSS_SELECTOR, f"#sessions li[data-session='{sid}']").click()
        _wait(d, lambda d: "Worst predicted ray sigma" in d.find_element(By.ID,
                                                                          "next-pose-text").text)
        _wait(d, lambda d: _loaded(d, "#next-pose-img") and _loaded(d, "#coverage"))
        # Each rig shows its live preview, or says clearly that there is none (404).
        for box in d.find_elements(By.CSS_SELECTOR, ".preview"):
            shown = d.execute_script("const i = arguments[0].querySelector('img');"
                                     "return !!i && i.naturalWidth > 0;", box)
            assert shown or "no preview" in box.text

        # Capture from the page at the suggested pose; progress comes from the SSE stream.
        d.find_element(By.ID, "use-suggestion").click()
        d.find_element(By.ID, "capture-btn").click()
        seen = set()

        def finished(d) -> bool:
            seen.add(d.find_element(By.ID, "progress").get_attribute("value"))
            return d.find_element(By.ID, "progress-text").get_attribute("data-status") in (
                "succeeded", "failed", "cancelled")

        _wait(d, lambda d: d.find_element(By.ID, "progress-text").get_attribute("data-status")
              == "running")
        _shot(d, "1-capture-running")
        _wait(d, finished)
        text = d.find_element(By.ID, "progress-text").text
        assert "succeeded" in text, text
        assert len(seen) >= 2, f"the progress bar never moved: {seen}"
        _wait(d, lambda d: len(d.find_elements(By.CSS_SELECTOR, "#poses tbody tr")) == 4)
        d.find_element(By.CSS_SELECTOR, "#poses tbody tr:last-child button").click()
        _wait(d, lambda d: all(_loaded(d, f"#pose-maps img:nth-of-type({i})")
                               for i in (1, 2, 3, 4)))
        _shot(d, "2-session-after-capture")

        # Start another capture and cancel it from the page.
        d.find_element(By.ID, "capture-btn").click()
        _wait(d, lambda d: d.find_element(By.ID, "progress-text").get_attribute("data-status")
              == "running")
        d.find_element(By.ID, "cancel-btn").click()
        _wait(d, lambda d: d.find_element(By.ID, "progress-text").get_attribute("data-status")
              in ("cancelled", "succeeded"))
        assert "cancelled" in d.find_element(By.ID, "progress-text").text

        Select(d.find_element(By.ID, "calibrate-model")).select_by_visible_text("opencv5")
        d.find_element(By.ID, "calibrate-btn").click()
        link = _wait(d, lambda d: d.find_element(By.CSS_SELECTOR, "a.report-link"), 300)
        _shot(d, "3-calibrated")
        d.get(link.get_attribute("href"))
        _wait(d, lambda d: d.execute_script(
            "return [...document.images].length >= 8 && "
            "[...document.images].every(i => i.complete && i.naturalWidth > 0)"), 300)
        assert "ray 1-sigma max" in d.page_source and "uncertainty.png" in d.page_source
        _shot(d, "4-report")
        api.close()
