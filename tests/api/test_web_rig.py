"""The operator page on a session of two simulated cameras, in headless Chromium (Debian
chromium + chromium-driver through selenium, as the single-camera page test): the starting
poses captured from the page, each camera's status, valid pixels and maps per pose, the next
pose naming the cameras it serves with a picture per camera and its outline drawn over each
served camera's preview, "Calibrate rig" (an error beside it first, with no poses),
the extrinsics with their sigma, and the opencv-stereo download read back by OpenCV.
Screenshots at 1400 and 800 px go to test-artifacts/web/ (rig-*.png)."""

from __future__ import annotations

import os
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pytest
from PIL import Image

from api.client import PhasecalClient
from api.config import ServiceConfig
from api.inprocess import running_service

CHROMIUM, DRIVER = "/usr/bin/chromium", "/usr/bin/chromedriver"
TOKEN = "rig-page-token"
ARTIFACTS = Path(__file__).resolve().parents[2] / "test-artifacts" / "web"
CONFIG = {"kind": "simulated", "screen": {"width_px": 320, "height_px": 240,
                                          "pitch_mm": [0.5, 0.5]},
          "cameras": [{"name": "left", "model": "mild_pinhole", "width": 96, "height": 72},
                      {"name": "right", "model": "mild_pinhole", "width": 96, "height": 72}]}


@pytest.fixture(scope="module")
def service(tmp_path_factory: pytest.TempPathFactory) -> Iterator[tuple[str, str]]:
    data = tmp_path_factory.mktemp("webrig") / "data"
    with running_service(ServiceConfig(data_dir=data, token=TOKEN, executor="threads")) as (url, _):
        api = PhasecalClient(url, token=TOKEN)
        rig = api.post("/rigs", {"name": "sim-pair", "config": CONFIG})
        yield url, rig["id"]
        api.close()


@pytest.fixture(scope="module")
def browser(tmp_path_factory: pytest.TempPathFactory) -> Iterator[tuple[Any, Path]]:
    if not (os.path.exists(CHROMIUM) and os.path.exists(DRIVER)):
        msg = "chromium and chromium-driver (Debian) are needed: scripts/install-system-deps.sh"
        if os.environ.get("CI"):
            pytest.fail(msg)
        pytest.skip(msg)
    from selenium import webdriver
    from selenium.webdriver.chrome.service import Service

    downloads = tmp_path_factory.mktemp("rig-downloads")
    opts = webdriver.ChromeOptions()
    opts.binary_location = CHROMIUM
    opts.page_load_strategy = "eager"
    for flag in ("--headless", "--no-sandbox", "--disable-gpu", "--disable-background-networking",
                 "--disable-component-update", "--no-first-run", "--window-size=1400,1000",
                 f"--user-data-dir={tmp_path_factory.mktemp('rig-profile')}"):
        opts.add_argument(flag)
    driver = webdriver.Chrome(service=Service(executable_path=DRIVER), options=opts)
    driver.execute_cdp_cmd("Browser.setDownloadBehavior",
                           {"behavior": "allow", "downloadPath": str(downloads)})
    yield driver, downloads
    driver.quit()


def wait(driver: Any, condition: Callable[[Any], Any], timeout: float = 300.0) -> Any:
    from selenium.webdriver.support.ui import WebDriverWait

    return WebDriverWait(driver, timeout, poll_frequency=0.2).until(condition)


def text(driver: Any, css: str) -> str:
    from selenium.webdriver.common.by import By

    found = driver.find_elements(By.CSS_SELECTOR, css)
    return found[0].text if found else ""


def click(driver: Any, css: str) -> None:
    from selenium.webdriver.common.by import By

    node = driver.find_element(By.CSS_SELECTOR, css)
    driver.execute_script("arguments[0].scrollIntoView({block: 'center'})", node)
    node.click()


def loaded(driver: Any, css: str) -> bool:
    return bool(driver.execute_script(
        "const i = document.querySelector(arguments[0]);"
        "return !!i && i.complete && i.naturalWidth > 0;", css))


def outline_pixels(driver: Any, camera: str) -> int:
    """Pixels of the suggested screen's outline (the overlay's yellow) over a camera's preview."""
    return int(driver.execute_script(
        "const c = document.querySelector(`figure.camera[data-camera=${arguments[0]}] canvas`);"
        "const d = c.getContext('2d').getImageData(0, 0, c.width, c.height).data; let n = 0;"
        "for (let i = 0; i < d.length; i += 4) {"
        "  if (d[i + 3] > 128 && d[i] > 200 && d[i + 1] > 150 && d[i + 2] < 90) n++; }"
        "return n;", camera))


def shots(driver: Any, name: str) -> None:
    """Full-page screenshots at 1400 and 800 px; none may be blank."""
    ARTIFACTS.mkdir(parents=True, exist_ok=True)
    for width in (1400, 800):
        driver.set_window_size(width, 900)
        height = driver.execute_script("return document.documentElement.scrollHeight")
        driver.set_window_size(width, min(max(height, 900), 5000))
        time.sleep(0.3)
        path = ARTIFACTS / f"rig-{name}-{width}.png"
        driver.save_screenshot(str(path))
        assert np.asarray(Image.open(path).convert("L"), dtype=float).std() > 20, path
    driver.set_window_size(1400, 1000)


def test_rig_session_from_the_page(service, browser) -> None:
    from selenium.webdriver.common.by import By
    from selenium.webdriver.support.ui import Select

    url, rig_id = service
    d, downloads = browser
    d.get(url + "/")
    d.find_element(By.ID, "token").send_keys(TOKEN)
    click(d, "#token-form button")
    wait(d, lambda d: text(d, "#status") == "ready")
    Select(d.find_element(By.ID, "new-session-rig")).select_by_value(rig_id)
    name = d.find_element(By.ID, "new-session-name")
    name.clear()
    name.send_keys("pair")
    click(d, "#new-session-btn")
    wait(d, lambda d: "Session pair" in text(d, "#session-title"))
    assert len(d.find_elements(By.CSS_SELECTOR, "#cameras .camera")) == 2
    assert text(d, "#calibrate-btn") == "Calibrate rig"
    for cam in ("left", "right"):
        Select(d.find_element(By.ID, f"rig-model-{cam}")).select_by_value("opencv5")
    # Calibrating with no poses: the refusal is explained beside the button.
    click(d, "#calibrate-btn")
    wait(d, lambda d: "no ready poses" in text(d, "#calibrate-feedback").lower())

    wait(d, lambda d: len(d.find_elements(By.CSS_SELECTOR, "#starting-list li")) >= 3)
    click(d, "#starting-btn")
    wait(d, lambda d: "starting poses captured" in text(d, "#starting-feedback"), 600)
    # the refusal said before the poses no longer stands beside the button
    assert "no ready poses" not in text(d, "#calibrate-feedback").lower()
    rows = d.find_elements(By.CSS_SELECTOR, "#poses tbody tr")
    assert len(rows) >= 3
    for row in rows:
        cams = row.find_elements(By.CSS_SELECTOR, ".rig-camera")
        assert [c.get_attribute("data-camera") for c in cams] == ["left", "right"]
        assert all("ready" in c.text and " px" in c.text for c in cams), [c.text for c in cams]
    click(d, "#poses tbody tr button")  # the first pose's maps, per camera
    wait(d, lambda d: loaded(d, ".rig-maps[data-camera=right] img")
         and loaded(d, ".rig-maps[data-camera=left] img"))
    wait(d, lambda d: "Serves:" in text(d, "#next-pose-serves"))
    served = text(d, "#next-pose-serves").split(":", 1)[1]
    assert {s.strip() for s in served.split(",")} <= {"left", "right"}
    assert len(d.find_elements(By.CSS_SELECTOR, ".rig-next li")) == 2
    for cam in ("left", "right"):  # each camera's picture beside its line
        wait(d, lambda d, cam=cam: loaded(d, f".rig-next li[data-camera={cam}] img"), 60)
    for cam in ("left", "right"):  # the screen's outline over each preview that sees it
        drawn = outline_pixels(d, cam)
        assert (drawn > 50) if cam in {s.strip() for s in served.split(",")} else drawn == 0, cam
    shots(d, "1-poses")

    click(d, "#calibrate-btn")
    wait(d, lambda d: "succeeded" in text(d, "#calibrate-feedback"), 600)
    wait(d, lambda d: d.find_elements(By.CSS_SELECTOR, "#rig-extrinsics tr[data-camera=right]"))
    cells = [c.text for c in d.find_elements(By.CSS_SELECTOR,
                                             "#rig-extrinsics tr[data-camera=right] td")]
    baseline, sigma_mm, sigma_mrad = float(cells[2]), float(cells[4]), float(cells[5])
    assert baseline > 1 and 0 < sigma_mm < baseline and sigma_mrad > 0
    shots(d, "2-calibrated")
    click(d, "li[data-rig-download='opencv-stereo left,right'] a")
    wait(d, lambda d: "Saved" in text(d, "#downloads-feedback"), 60)
    deadline = time.monotonic() + 30
    while not (found := [p for p in downloads.iterdir() if p.name.endswith("stereo.yaml")]):
        assert time.monotonic() < deadline, sorted(downloads.iterdir())
        time.sleep(0.2)
    fs = cv2.FileStorage(str(found[0]), cv2.FILE_STORAGE_READ)
    t = fs.getNode("T").mat().ravel()
    assert fs.getNode("K1").mat().shape == (3, 3)
    assert np.linalg.norm(t) == pytest.approx(baseline, rel=1e-3)
