"""The operator page runs the closed loop on a simulated rig whose arm carries the camera:
the panel shows only for a rig with a mover, the run's log grows on the page (poses taken,
the worst ray sigma after each, why it stopped), and its poses land in the pose table."""

from __future__ import annotations

from selenium.webdriver.common.by import By

from tests.api.test_web_browser import (
    _click,
    _feedback,
    _new_session,
    _open_page,
    _rows,
    _shots,
    _text,
    _wait,
    browser,  # noqa: F401  (fixtures)
    downloads,  # noqa: F401
    service,  # noqa: F401
)

ARM_RIG = {"kind": "simulated", "camera": {"width": 160, "height": 120},
           "mover": {"backend": "simulated-arm", "repeatability_mm": 0.01,
                     "repeatability_deg": 0.002, "speed_mm_s": 20000.0,
                     "speed_deg_s": 5000.0, "settle_s": 0.0}}


def test_the_closed_loop_from_the_page(service, browser) -> None:  # noqa: F811
    url, api, plain_rig = service
    arm = api.post("/rigs", {"name": "sim-arm", "config": ARM_RIG})["id"]
    d = browser
    _open_page(d, url)
    _new_session(d, plain_rig, "no-arm")
    assert not d.find_element(By.ID, "auto-panel").is_displayed()  # no mover: no panel
    _new_session(d, arm, "arm")
    _wait(d, lambda d: d.find_element(By.ID, "auto-panel").is_displayed())
    # the arm holds the view: the page offers no screen placing of its own
    assert not d.find_element(By.ID, "starting-btn").is_displayed()
    _wait(d, lambda d: "automatic run below" in _text(d, "#starting-text"))
    budget = d.find_element(By.ID, "auto-budget")
    budget.clear()
    budget.send_keys("5")
    before = _text(d, "#next-pose-text")  # no pose yet: guidance has nothing to plan from
    _click(d, "#auto-btn")
    _feedback(d, "#auto-feedback", "the run ended", 600)
    # the suggestion is asked for again with the run's poses
    _wait(d, lambda d: _text(d, "#next-pose-text") not in ("", before), 300)
    log = _text(d, "#auto-log")
    assert "stopped: budget spent" in log or "stopped: target met" in log, log
    assert "worst ray sigma then" in log and "flange at" in log
    assert _rows(d, "#poses") == 5
    _shots(d, "auto")
