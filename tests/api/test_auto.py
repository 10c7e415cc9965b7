"""The closed loop over REST on a simulated rig with an arm: the screen follows the arm
through a known hand-eye (the truth the hand-eye result is checked against from outside);
the loop stops at the target or the budget and reports its planned poses, skips poses
outside the workspace, stops the arm at once on cancel, and a rig without a mover is a 409."""

from __future__ import annotations

import json
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from fastapi.testclient import TestClient

from acquisition.mover import MoverInfo, RobotPose, Workspace
from acquisition.rig import open_rig
from api.app import create_app
from api.cli import main
from api.commands import auto as auto_command
from api.config import ServiceConfig
from hw_mocks.arm import HandEyeRig, SimulatedArm, SimulatedMover, handeye_rig

FAST = {"speed_mm_s": 20000.0, "speed_deg_s": 5000.0, "settle_s": 0.0}
RIG = {"kind": "simulated", "camera": {"width": 160, "height": 120},
       "mover": {"backend": "simulated-arm", "repeatability_mm": 0.01,
                 "repeatability_deg": 0.002, **FAST}}


class ScreenFollowsArm:
    """The rig's simulated arm, with the simulated screen placed after each move where the
    camera would see it through the hand-eye truth (the simulator's own set_pose)."""

    def __init__(self, truth: HandEyeRig, sim: Any) -> None:
        self.truth, self.sim = truth, sim

    @property
    def info(self) -> MoverInfo:
        return self.truth.arm.info

    def move_to(self, pose: RobotPose, timeout_s: float) -> RobotPose:
        try:
            return self.truth.arm.move_to(pose, timeout_s)
        finally:
            seen = self.truth.screen_pose()
            self.sim.set_pose(seen.rotation, seen.translation)

    def current_pose(self) -> RobotPose:
        return self.truth.arm.current_pose()

    def stop(self) -> None:
        self.truth.arm.stop()

    def close(self) -> None:
        self.truth.arm.close()


@pytest.fixture(scope="module")
def service(tmp_path_factory: pytest.TempPathFactory) -> Iterator[tuple[TestClient, Any]]:
    data = tmp_path_factory.mktemp("auto") / "data"
    app = create_app(ServiceConfig(data_dir=data, executor="threads"))
    with TestClient(app, raise_server_exceptions=False) as c:
        yield c, app.state.services


def follow_arm(rig: Any, seed: int, reach_mm: float | None = None,
            **motion: float) -> HandEyeRig:
    """Make the simulated screen follow `rig`'s arm (eye-in-hand, a random hand-eye truth)
    and stand the arm where the camera sees the screen; with `reach_mm` (or `motion`) the
    rig's arm is replaced by one whose workspace is a box of that half-width around that
    pose (or that moves at that pace)."""
    arm = rig.mover
    assert isinstance(arm, SimulatedMover)
    rng = np.random.default_rng(seed)
    made = handeye_rig("eye-in-hand", rig.simulated.truth_camera, rig.screen, rng)
    start = made.view_plan(1, rng)[0]
    if reach_mm is not None or motion:
        reach = 1500.0 if reach_mm is None else reach_mm
        box = Workspace(tuple(start.translation_mm - reach), tuple(start.translation_mm + reach))
        arm = SimulatedArm(workspace=box, start=start, rng=rng, **{**FAST, **motion})
    truth = HandEyeRig("eye-in-hand", arm, made.camera, made.screen, made.hand_eye,
                       made.world_target)
    rig.mover = ScreenFollowsArm(truth, rig.simulated)
    rig.mover.move_to(start, 5.0)
    return truth


def _arm_rig(c: TestClient, svc: Any, seed: int, reach_mm: float | None = None,
             **motion: float) -> tuple[str, HandEyeRig]:
    """A session on a new simulated rig with an arm the screen follows (`follow_arm`)."""
    rig_id = c.post("/rigs", json={"name": f"arm{seed}", "config": RIG}).json()["id"]
    truth = follow_arm(svc.rigs.handle(rig_id).rig, seed, reach_mm, **motion)
    sid = c.post("/sessions", json={"rig_id": rig_id, "preset": "fast"}).json()["id"]
    return sid, truth


def _wait(c: TestClient, job_id: str, timeout_s: float = 600) -> dict:
    end = time.monotonic() + timeout_s
    while time.monotonic() < end:
        state = c.get(f"/jobs/{job_id}").json()
        if state["status"] not in ("queued", "running"):
            return state
        time.sleep(0.1)
    raise AssertionError(f"job {job_id} did not end")


def test_auto_reaches_the_budget_with_planned_poses_and_a_true_hand_eye(service) -> None:
    c, svc = service
    sid, truth = _arm_rig(c, svc, 1)
    r = c.post(f"/sessions/{sid}/auto", json={
        "target": {"worst_ray_sigma_urad": 1e-3}, "budget": 6, "mount": "eye-in-hand",
        "model": "opencv5"})
    assert r.status_code == 202, r.text
    job = _wait(c, r.json()["id"])
    assert job["status"] == "succeeded", job
    log = job["result"]
    assert log["stop_reason"] == "budget spent" and len(log["poses"]) == 6
    assert [p["predicted_worst_ray_sigma_urad"] is None for p in log["poses"]] == \
        [True] * 4 + [False] * 2  # the starting set, then planned poses
    planned = log["poses"][4]
    assert planned["reason"].startswith("planned:") and planned["worst_ray_sigma_urad"] > 0
    sigma = log["handeye"]["sigma"]
    got = np.array(log["handeye"]["hand_eye"]["t_mm"])
    assert np.linalg.norm(got - truth.hand_eye.translation_mm) < 5 * sigma["translation_mm"]
    poses = c.get(f"/sessions/{sid}/poses").json()
    assert sum(p["status"] == "ready" for p in poses) == 6
    assert c.get(f"/sessions/{sid}/auto").json() == log
    assert c.get(f"/sessions/{sid}/handeye").json()["format"] == "phasecal.handeye/1"


def test_a_rig_without_a_mover_is_409_naming_the_fix(service) -> None:
    c, _ = service
    sid = c.post("/sessions", json={"preset": "fast"}).json()["id"]
    r = c.post(f"/sessions/{sid}/auto", json={"target": {"worst_ray_sigma_urad": 50},
                                              "budget": 8, "mount": "eye-in-hand"})
    assert r.status_code == 409 and "add a `mover` section" in r.json()["detail"]
    r = c.post(f"/sessions/{sid}/auto", json={"target": {"worst_ray_sigma_urad": 50},
                                              "budget": 8, "mount": "eye-in-hand",
                                              "workspace": {"min_mm": [0, 0, 0]}})
    assert r.status_code == 422 and "workspace" in r.json()["detail"]


def _start(c: TestClient, sid: str, **body: Any) -> str:
    r = c.post(f"/sessions/{sid}/auto", json={"target": {"worst_ray_sigma_urad": 1e-3},
                                              "budget": 6, "mount": "eye-in-hand", **body})
    assert r.status_code == 202, r.text
    return r.json()["id"]


def test_auto_stops_at_a_met_target(service) -> None:
    c, svc = service
    sid, _ = _arm_rig(c, svc, 2)
    job = _wait(c, _start(c, sid, target={"worst_ray_sigma_urad": 1e6,
                                          "handeye_sigma_mm": 100}))
    assert job["status"] == "succeeded", job
    log = job["result"]
    assert log["stop_reason"] == "target met" and len(log["poses"]) == 4
    assert log["handeye"]["sigma"]["translation_mm"] <= 100


def test_poses_the_mover_cannot_reach_are_skipped_and_the_next_best_taken(service) -> None:
    c, svc = service
    sid, truth = _arm_rig(c, svc, 3, reach_mm=60.0)
    job = _wait(c, _start(c, sid, budget=5))
    assert job["status"] == "succeeded", job
    log = job["result"]
    assert log["skipped"] and all("outside the workspace" in s["why"] for s in log["skipped"])
    box = truth.arm.info.workspace
    for pose in log["poses"]:
        assert box.why_unreachable(RobotPose.from_json(pose["flange"])) is None
    assert log["stop_reason"] in ("budget spent",
                                  "no reachable pose lowers the worst ray sigma further")


def test_cancel_mid_move_stops_the_arm_and_keeps_the_poses_taken(service) -> None:
    c, svc = service
    sid, truth = _arm_rig(c, svc, 4, speed_mm_s=1.0, speed_deg_s=0.5)  # a move takes 16 s
    job_id = _start(c, sid)
    end = time.monotonic() + 120
    while "pose 2/6: moving" not in c.get(f"/jobs/{job_id}").json()["stage"]:
        assert time.monotonic() < end, "the second pose's move never started"
        time.sleep(0.05)
    moving = c.get(f"/sessions/{sid}/auto").json()["moving_to"]
    assert moving["reason"].startswith("starting set: turn")  # the planned pose, while moving
    time.sleep(0.3)
    assert c.post(f"/jobs/{job_id}/cancel").status_code in (200, 202)
    job = _wait(c, job_id)
    assert job["status"] == "cancelled", job
    arm = truth.arm
    assert arm.moves == 2  # set-up and the first pose's; the second was stopped midway
    log = c.get(f"/sessions/{sid}/auto").json()
    assert log["stop_reason"] == "cancelled" and log["moving_to"] == moving  # where it went
    target = RobotPose.from_json(log["poses"][0]["flange"])
    assert 0 < arm.current_pose().angle_to_deg(target) < 7.9  # it stands where it stopped
    poses = c.get(f"/sessions/{sid}/poses").json()
    assert [p["status"] for p in poses] == ["ready"]
    assert log["poses"][0]["pose_id"] == poses[0]["id"]


def test_cli_auto_writes_poses_handeye_and_log(tmp_path: Path, monkeypatch, capsys) -> None:
    rig_toml = tmp_path / "rig.toml"
    rig_toml.write_text('kind = "simulated"\ncamera = {width = 160, height = 120}\n'
                        '[mover]\nbackend = "simulated-arm"\nspeed_mm_s = 20000\n'
                        'speed_deg_s = 5000\nsettle_s = 0\n')
    opened: list[HandEyeRig] = []

    def open_following(config: Any, **kwargs: Any) -> Any:
        rig = open_rig(config, **kwargs)
        opened.append(follow_arm(rig, 5))
        return rig

    monkeypatch.setattr(auto_command, "open_rig", open_following)
    out = tmp_path / "run"
    assert main(["auto", "--rig", str(rig_toml), "--target-sigma-urad", "1e6",
                 "--handeye-sigma-mm", "100", "--budget", "5", "-o", str(out)]) == 0
    printed = capsys.readouterr().out
    assert "stopped: target met" in printed and "hand-eye t_mm" in printed
    log = json.loads((out / "auto.json").read_text())
    assert [p["pose_id"] for p in log["poses"]] == [f"pose-{k:02d}" for k in range(4)]
    assert all((out / f"pose-{k:02d}" / "maps.npz").is_file() for k in range(4))
    assert json.loads((out / "handeye.json").read_text())["format"] == "phasecal.handeye/1"
    assert set(json.loads((out / "robot-poses.json").read_text())["poses"]) == \
        {f"pose-{k:02d}" for k in range(4)}


def test_cli_auto_refusals_are_one_line(tmp_path: Path, capsys) -> None:
    plain = tmp_path / "plain.toml"
    plain.write_text('kind = "simulated"\ncamera = {width = 32, height = 24}\n')
    cases = [(["--budget", "3"], "--budget: the starting set alone takes 4 poses"),
             (["--budget", "6"], "the rig has no mover: add a `mover` section")]
    for extra, needle in cases:
        assert main(["auto", "--rig", str(plain), "--target-sigma-urad", "50", *extra,
                     "-o", str(tmp_path / "x")]) == 1
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and needle in err[0], err
    assert not (tmp_path / "x").exists()
