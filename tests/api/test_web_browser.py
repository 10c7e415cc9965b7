"""The operator's web page in a real headless Chromium (Debian chromium + chromium-driver,
driven by selenium; nothing is downloaded at run time).

A newcomer's calibration from the page alone, on the simulated rig: a new session, the
starting poses the page moves the screen through, a guided pose, a calibration with a
held-out pose, the report, the OpenCV YAML and mrcal downloads read back by their readers, a
comparison of two fits, reload with the state in the URL (guidance and both fits use
opencv5, the cheapest model: what is checked is the page, not the model). And the errors a
newcomer meets (calibrating with no poses or too few, repeating a pose, a failed fit, a
wrong token), each explained next to the action that caused it. Screenshots of each state
at 1400 and 800 px wide go to test-artifacts/web/ (ignored by git) and are checked not to
be blank.
"""

from __future__ import annotations

import os
import subprocess
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
from calibration import load_model
from calibration.mrcal_io import read_cameramodel
from tests.api.test_api_session import small_rig
from tests.calibration.test_exports import SYSTEM_PYTHON, mrcal_available

CHROMIUM, DRIVER = "/usr/bin/chromium", "/usr/bin/chromedriver"
TOKEN = "page-test-token"
ARTIFACTS = Path(__file__).resolve().parents[2] / "test-artifacts" / "web"
WIDTHS = (1400, 800)


@pytest.fixture(scope="module")
def service(tmp_path_factory: pytest.TempPathFactory) -> Iterator[tuple[str, PhasecalClient, str]]:
    """The service with a token and a small simulated rig (on its virtual clock: captures
    take a fraction of a second)."""
    data = tmp_path_factory.mktemp("web") / "data"
    with running_service(ServiceConfig(data_dir=data, token=TOKEN, executor="threads")) as (url, _):
        api = PhasecalClient(url, token=TOKEN)
        rig = api.post("/rigs", {"name": "sim-small", "config": small_rig()})
        yield url, api, rig["id"]
        api.close()


@pytest.fixture(scope="module")
def downloads(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return tmp_path_factory.mktemp("downloads")


@pytest.fixture(scope="module")
def browser(tmp_path_factory: pytest.TempPathFactory, downloads: Path):
    if not (os.path.exists(CHROMIUM) and os.path.exists(DRIVER)):
        msg = "chromium and chromium-driver (Debian) are needed: scripts/install-system-deps.sh"
        if os.environ.get("CI"):
            pytest.fail(msg)
        pytest.skip(msg)
    from selenium import webdriver
    from selenium.webdriver.chrome.service import Service

    for old in ARTIFACTS.glob("[0-9]-*.png"):  # this test's shots only (the rig test's stay)
        old.unlink()
    opts = webdriver.ChromeOptions()
    opts.binary_location = CHROMIUM
    opts.page_load_strategy = "eager"
    profile = tmp_path_factory.mktemp("chromium-profile")
    for flag in ("--headless", "--no-sandbox", "--disable-gpu", "--disable-background-networking",
                 "--disable-component-update", "--no-first-run", f"--window-size={WIDTHS[0]},1000",
                 f"--user-data-dir={profile}"):
        opts.add_argument(flag)
    opts.add_experimental_option("prefs", {"download.default_directory": str(downloads),
                                           "download.prompt_for_download": False})
    driver = webdriver.Chrome(service=Service(executable_path=DRIVER), options=opts)
    driver.execute_cdp_cmd("Browser.setDownloadBehavior",
                           {"behavior": "allow", "downloadPath": str(downloads)})
    driver.set_page_load_timeout(60)
    yield driver
    driver.quit()


def _wait(driver, condition: Callable[[Any], Any], timeout: float = 180.0) -> Any:
    from selenium.webdriver.support.ui import WebDriverWait

    return WebDriverWait(driver, timeout, poll_frequency=0.2).until(condition)


def _shots(driver, name: str) -> None:
    """Full-page screenshots at each width; none may be blank."""
    ARTIFACTS.mkdir(parents=True, exist_ok=True)
    for width in WIDTHS:
        driver.set_window_size(width, 900)
        height = driver.execute_script("return document.documentElement.scrollHeight")
        driver.set_window_size(width, min(max(height, 900), 5000))
        time.sleep(0.3)  # layout and the preview's overlay follow the resize
        path = ARTIFACTS / f"{name}-{width}.png"
        driver.save_screenshot(str(path))
        img = np.asarray(Image.open(path).convert("L"), dtype=np.float64)
        assert img.std() > 20, f"{path} looks blank"
    driver.set_window_size(WIDTHS[0], 1000)


def _text(driver, css: str) -> str:
    from selenium.webdriver.common.by import By

    return driver.find_element(By.CSS_SELECTOR, css).text


def _click(driver, css: str) -> None:
    from selenium.webdriver.common.by import By

    node = driver.find_element(By.CSS_SELECTOR, css)
    driver.execute_script("arguments[0].scrollIntoView({block: 'center'})", node)
    node.click()


def _loaded(driver, css: str) -> bool:
    return bool(driver.execute_script(
        "const i = document.querySelector(arguments[0]);"
        "return !!i && !i.hidden && i.complete && i.naturalWidth > 0;", css))


def _feedback(driver, box: str, words: str, timeout: float = 180.0) -> str:
    """Wait for `words` in the feedback box next to an action; its text."""
    _wait(driver, lambda d: words.lower() in _text(d, box).lower(), timeout)
    return _text(driver, box)


def _open_page(driver, url: str) -> None:
    from selenium.webdriver.common.by import By

    driver.get(url + "/")
    token = driver.find_element(By.ID, "token")
    token.clear()
    token.send_keys(TOKEN)
    _click(driver, "#token-form button")
    _wait(driver, lambda d: _text(d, "#status") == "ready")


def _new_session(driver, rig_id: str, name: str) -> str:
    from selenium.webdriver.common.by import By
    from selenium.webdriver.support.ui import Select

    Select(driver.find_element(By.ID, "new-session-rig")).select_by_value(rig_id)
    name_box = driver.find_element(By.ID, "new-session-name")
    name_box.clear()
    name_box.send_keys(name)
    _click(driver, "#new-session-btn")
    _wait(driver, lambda d: f"Session {name}" in _text(d, "#session-title"))
    return _wait(driver, lambda d: d.find_element(By.CSS_SELECTOR, "#sessions li.current")
                 ).get_attribute("data-session")


def _accept_confirm(driver) -> None:
    from selenium.webdriver.support import expected_conditions as ec

    _wait(driver, ec.alert_is_present(), 10)
    driver.switch_to.alert.accept()


def _rows(driver, table: str) -> int:
    from selenium.webdriver.common.by import By

    return len(driver.find_elements(By.CSS_SELECTOR, f"{table} tbody tr"))


def _downloaded(folder: Path, suffix: str) -> Path:
    """The finished download whose name ends with `suffix`."""
    deadline = time.monotonic() + 60
    while time.monotonic() < deadline:
        done = [p for p in folder.iterdir() if p.name.endswith(suffix)]
        if done and not any(p.name.endswith(".crdownload") for p in folder.iterdir()):
            return done[0]
        time.sleep(0.2)
    raise AssertionError(f"no download ending {suffix!r} in {sorted(folder.iterdir())}")


def test_calibration_from_the_page_alone(service, browser, downloads: Path) -> None:
    from selenium.webdriver.common.by import By
    from selenium.webdriver.support.ui import Select

    url, api, rig_id = service
    d = browser
    _open_page(d, url)
    assert not d.find_element(By.ID, "sim-hint").get_attribute("hidden")
    assert "phasecal serve --rig rig.toml" in _text(d, "#sim-hint")
    sid = _new_session(d, rig_id, "newcomer")
    assert f"session={sid}" in d.current_url
    # the camera is idle: a clear state, not noise
    _wait(d, lambda d: "camera idle" in _text(d, ".camera").lower()
          or "live" in _text(d, ".camera figcaption"))
    _wait(d, lambda d: len(d.find_elements(By.CSS_SELECTOR, "#starting-list li")) >= 3)
    _shots(d, "1-new-session")

    # The starting poses: the page moves the simulated screen through a varied set. The
    # model chosen for calibrating is also the one guidance plans with.
    Select(d.find_element(By.ID, "calibrate-model")).select_by_value("opencv5")
    starting = len(d.find_elements(By.CSS_SELECTOR, "#starting-list li"))
    _click(d, "#starting-btn")
    _feedback(d, "#starting-feedback", "starting pose 1 of")
    _shots(d, "2-capturing-starting-poses")
    _feedback(d, "#starting-feedback", "starting poses captured", 600)
    assert _rows(d, "#poses") == starting
    assert all(li.get_attribute("data-captured") == "yes"
               for li in d.find_elements(By.CSS_SELECTOR, "#starting-list li"))
    assert not d.find_elements(By.CSS_SELECTOR, "#variety [data-duplicate]")

    # A guided pose: the suggested placement, then a new picture for the new plan.
    _wait(d, lambda d: "ray sigma" in _text(d, "#next-pose-text") and _loaded(d, "#next-pose-img"))
    first_plan = d.find_element(By.ID, "next-pose-img").get_attribute("src")
    _click(d, "#use-suggestion")
    _click(d, "#capture-btn")
    _feedback(d, "#capture-feedback", "succeeded", 300)
    _wait(d, lambda d: _loaded(d, "#next-pose-img")
          and d.find_element(By.ID, "next-pose-img").get_attribute("src") != first_plan)
    assert _rows(d, "#poses") == starting + 1
    # the suggested placement is drawn over the camera preview (what hardware users follow)
    assert d.execute_script(
        "const c = document.querySelector('.camera canvas.overlay');"
        "const px = c.getContext('2d').getImageData(0, 0, c.width, c.height).data;"
        "let n = 0; for (let i = 0; i < px.length; i += 4)"
        " if (px[i] > 200 && px[i + 1] > 150 && px[i + 2] < 80 && px[i + 3] > 0) n++;"
        "return n;") > 50
    _shots(d, "3-guided")

    # Calibrate with the first pose held out; the progress bar is in view while it runs.
    first_pose = d.find_element(By.CSS_SELECTOR, "#poses tbody tr").get_attribute("data-pose")
    _click(d, f"#poses tr[data-pose='{first_pose}'] input[type=checkbox]")
    assert "1 held out" in _text(d, "#heldout-summary")
    _click(d, "#calibrate-btn")
    _wait(d, lambda d: d.execute_script(
        "const r = document.querySelector('#cal-progress').getBoundingClientRect();"
        "return r.top >= 0 && r.bottom <= window.innerHeight;"))
    _feedback(d, "#calibrate-feedback", "succeeded", 600)
    cal = d.find_element(By.CSS_SELECTOR, "#calibrations tbody tr"
                         ).get_attribute("data-calibration")
    assert api.get(f"/calibrations/{cal}")["heldout_pose_ids"] == [first_pose]
    assert f"calibration={cal}" in d.current_url
    _shots(d, "4-calibrated")

    # Downloads, each read back by its consumer.
    k = load_model(api.download_file(cal, "model.json", downloads.parent / f"{cal}.json")
                   ).camera_matrix
    _click(d, "#downloads li[data-format='opencv-yaml'] a")
    _feedback(d, "#downloads-feedback", "saved")
    fs = cv2.FileStorage(str(_downloaded(downloads, "opencv.yaml")), cv2.FILE_STORAGE_READ)
    np.testing.assert_allclose(fs.getNode("camera_matrix").mat(), k, rtol=1e-9)
    fs.release()
    _click(d, "#downloads li[data-format='mrcal'] a")
    _feedback(d, "#downloads-feedback", ".cameramodel")
    cameramodel = _downloaded(downloads, ".cameramodel")
    np.testing.assert_allclose(read_cameramodel(cameramodel).camera_matrix, k, rtol=1e-9)
    if os.environ.get("CI") or mrcal_available():  # in CI always: mrcal itself (Debian's
        # python3-mrcal, in the system Python) reads the download
        script = ("import mrcal, sys\n"
                  "lens, p = mrcal.cameramodel(sys.argv[1]).intrinsics()\n"
                  "print(lens, *p[:4])")
        out = subprocess.run([SYSTEM_PYTHON, "-c", script, str(cameramodel)], check=True,
                             capture_output=True, text=True).stdout.split()
        assert out[0].startswith("LENSMODEL_")
        np.testing.assert_allclose([float(v) for v in out[1:5]],
                                   [k[0, 0], k[1, 1], k[0, 2], k[1, 2]], rtol=1e-9)
    _click(d, "#downloads a[href$='download=1']")
    _feedback(d, "#downloads-feedback", ".html")
    page = _downloaded(downloads, ".html").read_text(encoding="utf-8")
    assert cal in page and "data:image/png;base64," in page  # one file, pictures inside

    # A second fit (every pose), then the two compared from the page.
    _click(d, f"#poses tr[data-pose='{first_pose}'] input[type=checkbox]")
    _click(d, "#calibrate-btn")
    _feedback(d, "#calibrate-feedback", "succeeded", 600)
    _click(d, f"#calibrations tr[data-calibration='{cal}'] button.open-cal")
    Select(d.find_element(By.ID, "compare-with")).select_by_index(0)
    _click(d, "#compare-btn")
    _wait(d, lambda d: "urad" in _text(d, "#compare-result"), 300)
    compare_link = d.find_element(By.CSS_SELECTOR, "#compare-result a").get_attribute("href")
    _shots(d, "5-compared")

    # A long fit cancelled from its own panel.
    Select(d.find_element(By.ID, "calibrate-model")).select_by_value("sgcc")
    _click(d, "#calibrate-btn")
    _wait(d, lambda d: d.find_element(By.ID, "cal-cancel-btn").is_enabled())
    assert not d.find_element(By.ID, "cancel-btn").is_enabled()  # only the running job's
    _click(d, "#cal-cancel-btn")
    _feedback(d, "#calibrate-feedback", "cancelled", 300)

    # Reload: the session and the calibration come back from the URL.
    d.refresh()
    _wait(d, lambda d: _text(d, "#status") == "ready")
    assert sid in _text(d, "#session-title")
    _wait(d, lambda d: cal in _text(d, "#calibration-title"))

    # The report, and the comparison it links.
    report = d.find_element(By.CSS_SELECTOR, f"#calibrations tr[data-calibration='{cal}'] "
                                             "a.report-link").get_attribute("href")
    d.get(report)
    _wait(d, lambda d: d.execute_script(
        "return [...document.images].length >= 4 && "
        "[...document.images].every(i => i.complete && i.naturalWidth > 0)"), 300)
    _shots(d, "6-report")
    d.get(compare_link)
    _wait(d, lambda d: d.execute_script(
        "return document.readyState === 'complete' && "
        "[...document.images].every(i => i.complete && i.naturalWidth > 0)"), 300)
    _shots(d, "7-comparison")


def test_errors_are_explained_next_to_their_action(service, browser) -> None:
    from selenium.webdriver.common.by import By
    from selenium.webdriver.support.ui import Select

    url, api, rig_id = service
    d = browser
    _open_page(d, url)
    sid = _new_session(d, rig_id, "mistakes")
    unlabelled = d.execute_script(
        "return [...document.querySelectorAll('input, select, button')]"
        ".filter(e => !(e.labels && e.labels.length) && !e.getAttribute('aria-label')"
        " && !e.textContent.trim()).map(e => e.outerHTML)")
    assert not unlabelled, f"controls without a label: {unlabelled}"

    # Calibrating with no poses at all.
    Select(d.find_element(By.ID, "calibrate-model")).select_by_value("sgcc")
    _click(d, "#calibrate-btn")
    said = _feedback(d, "#calibrate-feedback", "no ready poses")
    assert "capture poses first" in said.lower()
    assert "no-poses" in d.find_element(By.CSS_SELECTOR, "#calibrate-feedback details"
                                        ).get_attribute("textContent")
    assert "guidance needs" in _text(d, "#next-pose-text").lower()

    # The same pose twice: the second repeats the first, and the page says so at once.
    for n in (1, 2):
        _click(d, "#capture-btn")
        _feedback(d, "#capture-feedback", "succeeded" if n == 1 else "repeats", 300)
    assert "move or tilt the screen" in _text(d, "#capture-feedback").lower()
    assert d.find_elements(By.CSS_SELECTOR, "#variety [data-duplicate]")

    # Too few poses for sgcc: how many it needs and what to do.
    _click(d, "#calibrate-btn")
    said = _feedback(d, "#calibrate-feedback", "needs at least 3 poses")
    assert "2 are ready" in said
    _shots(d, "8-errors")

    # Deleting the repeat from the page, with a confirmation.
    before = _rows(d, "#poses")
    _click(d, "#variety [data-duplicate] button")
    _accept_confirm(d)
    _feedback(d, "#poses-feedback", "deleted")
    _wait(d, lambda d: _rows(d, "#poses") == before - 1)
    assert len(api.get(f"/sessions/{sid}/poses")) == before - 1

    # A wrong token: the page says what to do where the token is entered.
    token = d.find_element(By.ID, "token")
    token.clear()
    token.send_keys("wrong")
    _click(d, "#token-form button")
    _wait(d, lambda d: "api token" in _text(d, "#status").lower())
    _shots(d, "9-wrong-token")
