"""phasecal as Bluesky devices: a RunEngine runs `calibration_session` against an in-process
service on a small simulated rig (documents carry the poses and the fit), a run stopped
mid-capture cancels the capture job, and the service's refusals surface with its reason."""

from __future__ import annotations

import asyncio
import importlib
import json
import re
import threading
import time
from collections import defaultdict
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
from bluesky import RunEngine
from bluesky import plan_stubs as bps
from bluesky.utils import FailedStatus, RunEngineInterrupted
from ophyd_async.plan_stubs import ensure_connected

import api.bluesky
from api.bluesky.devices import (
    PhasecalCalibration,
    PhasecalCapture,
    PhasecalGuide,
    PhasecalScreen,
    resource_id,
)
from api.bluesky.errors import PhasecalDeviceError
from api.bluesky.plans import calibration_session
from api.client import AsyncPhasecalClient, PhasecalClient
from api.config import ServiceConfig
from api.inprocess import running_service
from calibration import extras
from calibration.models.base import model_from_dict
from calibration.shared.maps import load_maps
from tests.api.test_api_session import H, W, screen_poses, small_rig, truth_camera


class Documents:
    """Every document a run emitted, by kind, and the events by stream name."""

    def __init__(self) -> None:
        self.by_kind: dict[str, list[dict]] = defaultdict(list)
        self.streams: dict[str, str] = {}  # descriptor uid -> stream name

    def __call__(self, name: str, doc: dict) -> None:
        self.by_kind[name].append(doc)
        if name == "descriptor":
            self.streams[doc["uid"]] = doc["name"]

    def events(self, stream: str) -> list[dict]:
        return [e for e in self.by_kind["event"] if self.streams[e["descriptor"]] == stream]

    def descriptor(self, stream: str) -> dict:
        return next(d for d in self.by_kind["descriptor"] if d["name"] == stream)


@pytest.fixture(scope="module")
def service(tmp_path_factory: pytest.TempPathFactory) -> Iterator[str]:
    root: Path = tmp_path_factory.mktemp("bluesky")
    with running_service(ServiceConfig(data_dir=root / "data")) as (url, _app):
        yield url


@pytest.fixture(scope="module")
def client(service: str) -> Iterator[PhasecalClient]:
    with PhasecalClient(service) as c:
        yield c


@pytest.fixture(scope="module")
def engine() -> RunEngine:
    return RunEngine({}, call_returns_result=True)


@pytest.fixture(scope="module")
def aclient(service: str, engine: RunEngine) -> Iterator[AsyncPhasecalClient]:
    c = AsyncPhasecalClient(service)
    yield c
    asyncio.run_coroutine_threadsafe(c.close(), engine.loop).result()


def rig(client: PhasecalClient, slow: bool = False) -> str:
    return client.post("/rigs", {"name": "bluesky", "config": small_rig(slow=slow)})["id"]


def test_guided_session_documents_carry_poses_and_fit(client, aclient, engine) -> None:
    rig_id = rig(client)
    capture = PhasecalCapture(aclient, rig_id, preset="fast", name="phasecal")
    screen = PhasecalScreen(aclient, rig_id, name="screen")
    guide = PhasecalGuide(capture, model="opencv5", starting_count=3, name="guide")
    fit = PhasecalCalibration(capture, model="opencv5", name="fit")
    docs = Documents()
    result = engine(calibration_session(capture, screen, fit, guide=guide, pose_count=4,
                                        heldout=1, md={"operator": "test"}), docs)
    assert result.exit_status == "success", result
    (start,) = docs.by_kind["start"]
    (stop,) = docs.by_kind["stop"]
    assert stop["exit_status"] == "success"
    session_id = start["phasecal_session_id"]
    assert start["operator"] == "test" and start["phasecal_model"] == "opencv5"

    # each pose: the screen went where the guide said; the reading is the service's pose
    guidance, captures = docs.events("guidance"), docs.events("primary")
    assert [g["data"]["guide-source"] for g in guidance] == ["starting-poses"] * 3 + [
        "next-pose"]
    assert np.isfinite(guidance[-1]["data"]["guide-predicted_sigma_urad"])
    poses = {p["id"]: p for p in client.get(f"/sessions/{session_id}/poses")}
    assert len(captures) == len(poses) == 4
    for g, ev in zip(guidance, captures, strict=True):
        pose = poses[ev["data"]["phasecal-pose_id"]]
        assert pose["status"] == ev["data"]["phasecal-status"] == "ready"
        assert ev["data"]["phasecal-valid_pixels"] == pose["valid_pixels"] > 0.1 * W * H
        assert np.allclose(ev["data"]["screen-tvec_mm"], g["data"]["guide-tvec_mm"])
        assert np.allclose(ev["data"]["screen-rvec"], g["data"]["guide-rvec"])
        maps = load_maps(client.request("GET", ev["data"]["phasecal-maps_url"]).content)
        assert maps.meta["pose_id"] == pose["id"]
    keys = docs.descriptor("primary")["data_keys"]
    assert keys["phasecal-valid_pixels"]["dtype"] == "integer"
    assert keys["phasecal-valid_pixels"]["units"] == "px"
    assert keys["screen-tvec_mm"]["shape"] == [3]
    config = docs.descriptor("primary")["configuration"]["phasecal"]["data"]
    assert config["phasecal-session_id"] == session_id

    # the fit: one event whose statistics are the service's, held-out pose scored
    (event,) = docs.events("calibration")
    cal = client.get(f"/calibrations/{result.plan_result}")
    assert event["data"]["fit-calibration_id"] == cal["id"]
    assert cal["status"] == event["data"]["fit-status"] == "succeeded"
    assert cal["heldout_pose_ids"] == [captures[-1]["data"]["phasecal-pose_id"]]
    assert json.loads(event["data"]["fit-stats"]) == cal["stats"]
    assert event["data"]["fit-rms_px"] == cal["stats"]["rms_px"] < 0.5
    assert np.isfinite(event["data"]["fit-heldout_rms_px"])
    fit_config = docs.descriptor("calibration")["configuration"]["fit"]["data"]
    assert fit_config["fit-model"] == "opencv5"
    # and the model it names sees the simulated camera's rays
    model = model_from_dict(client.get(f"/calibrations/{cal['id']}/files/model.json"))
    u, v = np.meshgrid(np.linspace(10, W - 10, 7), np.linspace(10, H - 10, 5))
    _, rays = model.unproject(np.stack([u.ravel(), v.ravel()], axis=1))
    _, true_rays = truth_camera().rays(u.ravel(), v.ravel())
    assert np.median(np.arccos(np.clip(np.sum(rays * true_rays, axis=1), -1, 1))) < 2e-3


def pause_mid_capture(client: PhasecalClient, engine: RunEngine, plan, docs: Documents
                      ) -> dict:
    """Run `plan` and pause the engine once a capture has taken two frames; that job."""
    running: dict = {}

    def pause_when_capturing() -> None:
        deadline = time.monotonic() + 120
        while time.monotonic() < deadline:
            for job in client.get("/jobs", kind="capture", status="running")["items"]:
                if job["stage"] == "capture" and job["done"] >= 2:
                    running.update(job)
                    engine.request_pause(defer=False)
                    return
            time.sleep(0.05)

    watcher = threading.Thread(target=pause_when_capturing)
    watcher.start()
    try:
        with pytest.raises(RunEngineInterrupted):
            engine(plan, docs)
    finally:
        watcher.join()
    assert running, "the capture never started"
    final = client.wait(running["id"], check=False, timeout_s=60)
    assert final["status"] == "cancelled"  # already while paused: the rig is free
    assert client.get(final["resource"])["status"] == "cancelled"
    return final


@pytest.mark.parametrize(("end", "exit_status"), [("stop", "success"), ("abort", "abort")])
def test_stopped_run_cancels_the_capture(client, aclient, engine, end, exit_status) -> None:
    rig_id = rig(client, slow=True)
    capture = PhasecalCapture(aclient, rig_id, preset="fast", name="phasecal")
    screen = PhasecalScreen(aclient, rig_id, name="screen")
    fit = PhasecalCalibration(capture, name="fit")
    docs = Documents()
    pause_mid_capture(client, engine,
                      calibration_session(capture, screen, fit, screen_poses(3, seed=5)), docs)
    getattr(engine, end)()
    assert client.get("/jobs", status="running")["items"] == []
    assert client.get("/jobs", status="queued")["items"] == []
    assert docs.by_kind["stop"][0]["exit_status"] == exit_status
    assert docs.events("primary") == [] and docs.events("calibration") == []


def test_paused_run_resumes_by_capturing_the_pose_again(client, aclient, engine) -> None:
    rig_id = rig(client, slow=True)
    capture = PhasecalCapture(aclient, rig_id, preset="fast", name="phasecal")
    screen = PhasecalScreen(aclient, rig_id, name="screen")
    guide = PhasecalGuide(capture, model="opencv5", starting_count=3, name="guide")
    fit = PhasecalCalibration(capture, name="fit")
    docs = Documents()
    cancelled = pause_mid_capture(
        client, engine, calibration_session(capture, screen, fit, guide=guide, pose_count=3),
        docs)
    result = engine.resume()
    assert result.exit_status == "success"
    ids = [e["data"]["phasecal-pose_id"] for e in docs.events("primary")]
    session_id = docs.by_kind["start"][0]["phasecal_session_id"]
    poses = {p["id"]: p["status"] for p in client.get(f"/sessions/{session_id}/poses")}
    assert resource_id(cancelled) not in ids and poses.pop(resource_id(cancelled)) == "cancelled"
    assert len(ids) == 3 and poses == dict.fromkeys(ids, "ready")
    cal = client.get(f"/calibrations/{result.plan_result}")
    assert cal["status"] == "succeeded" and cal["pose_ids"] == ids
    # the replayed guide suggested the interrupted pose again: the three starting poses,
    # each captured once, in the order suggested
    suggested = [tuple(g["data"]["guide-tvec_mm"]) for g in docs.events("guidance")]
    assert len(suggested) == 4 and len(set(suggested)) == 3
    shown = [tuple(e["data"]["screen-tvec_mm"]) for e in docs.events("primary")]
    assert shown == list(dict.fromkeys(suggested))


def test_capture_past_its_timeout_is_cancelled(client, aclient, engine) -> None:
    rig_id = rig(client, slow=True)
    capture = PhasecalCapture(aclient, rig_id, preset="fast", capture_timeout_s=0.5,
                              name="phasecal")
    screen = PhasecalScreen(aclient, rig_id, name="screen")
    fit = PhasecalCalibration(capture, name="fit")
    with pytest.raises(FailedStatus) as failed:
        engine(calibration_session(capture, screen, fit, screen_poses(3, seed=5)))
    cause = failed.value.__cause__
    assert isinstance(cause, PhasecalDeviceError)
    job_id = re.fullmatch(r"job (\S+) \(capture\) did not end within 0.5 s; it was "
                          r"cancelled on the service", str(cause)).group(1)
    assert client.wait(job_id, check=False, timeout_s=60)["status"] == "cancelled"


def test_service_refusal_surfaces_with_its_reason(client, aclient, engine) -> None:
    capture = PhasecalCapture(aclient, session_id="no-such-session", name="phasecal")
    screen = PhasecalScreen(aclient, "no-such-rig", name="screen")
    fit = PhasecalCalibration(capture, name="fit")
    with pytest.raises(FailedStatus) as failed:
        engine(calibration_session(capture, screen, fit, screen_poses(3, seed=5)))
    cause = failed.value.__cause__
    assert isinstance(cause, PhasecalDeviceError) and cause.status == 404
    assert re.fullmatch(r"phasecal: attaching to session no-such-session failed: .*"
                        r"no-such-session.* \(HTTP 404 not-found\)", str(cause))
    with pytest.raises(FailedStatus) as failed:
        engine(screen_move(screen))
    cause = failed.value.__cause__
    assert isinstance(cause, PhasecalDeviceError) and cause.status == 404
    assert "moving the screen of rig no-such-rig" in str(cause)
    assert cause.problem["detail"] in str(cause)
    with pytest.raises(ValueError, match=r"heldout must be in \[0, 2\] for 3 poses, got 3"):
        engine(calibration_session(capture, screen, fit, screen_poses(3, seed=5), heldout=3))
    with pytest.raises(ValueError, match="tvec_mm must be 3 finite numbers"):
        engine(calibration_session(capture, screen, fit,
                                   [{"rvec": [0, 0, 0], "tvec_mm": [0, 0]}]))


def screen_move(screen: PhasecalScreen):
    yield from ensure_connected(screen)
    yield from bps.mv(screen, screen_poses(1, seed=3)[0])


def test_without_the_extra_the_import_names_the_install_command(monkeypatch) -> None:
    monkeypatch.setattr(extras, "installed", lambda extra: extra != "bluesky")
    with pytest.raises(extras.MissingExtra, match=r"pip install 'phasecal\[bluesky\]'"):
        importlib.reload(api.bluesky)
