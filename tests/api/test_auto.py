"""The closed loop over REST and the CLI on a simulated rig whose arm carries the camera
(the simulator's coupling; its hand-eye truth, `SimulatorTruth.handeye`, is what the
result is checked against from outside);
the loop stops at the target or the budget and reports its planned poses, skips poses
outside the workspace, stops the arm at once on cancel, and a rig without a mover is a 409."""

from __future__ import annotations

import json
import time
import tomllib
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from fastapi.testclient import TestClient

from acquisition.mover import RobotPose
from acquisition.rig import open_rig, parse_rig_config
from api.app import create_app
from api.cli import main
from api.config import ServiceConfig
from api.jobs.auto import AutoLoop
from calibration.shared.maps import save_maps
from calibration.shared.progress import TaskContext
from hw_mocks.rig import open_simulated_rig
from hw_mocks.truth import SimulatorTruth, perfect_maps

FAST = {"speed_mm_s": 20000.0, "speed_deg_s": 5000.0, "settle_s": 0.0}
RIG = {"kind": "simulated", "camera": {"width": 160, "height": 120},
       "mover": {"backend": "simulated-arm", "repeatability_mm": 0.01,
                 "repeatability_deg": 0.002, **FAST}}


@pytest.fixture(scope="module")
def service(tmp_path_factory: pytest.TempPathFactory) -> Iterator[tuple[TestClient, Any]]:
    data = tmp_path_factory.mktemp("auto") / "data"
    app = create_app(ServiceConfig(data_dir=data, executor="threads"))
    with TestClient(app, raise_server_exceptions=False) as c:
        yield c, app.state.services


def _arm_rig(c: TestClient, seed: int, reach_mm: float | None = None,
             **motion: float) -> tuple[str, dict[str, Any]]:
    """A session on a new simulated rig whose arm carries the camera (the rig's own
    coupling); with `reach_mm` the arm's workspace is a box of that half-width around its
    home pose (the origin), with `motion` it moves at that pace. Returns the rig config."""
    mover: dict[str, Any] = {**RIG["mover"], **motion, "seed": seed}
    if reach_mm is not None:
        mover["workspace"] = {"min_mm": [-reach_mm] * 3, "max_mm": [reach_mm] * 3}
    config = {**RIG, "mover": mover}
    rig_id = c.post("/rigs", json={"name": f"arm{seed}", "config": config}).json()["id"]
    sid = c.post("/sessions", json={"rig_id": rig_id, "preset": "fast"}).json()["id"]
    return sid, config


def _wait(c: TestClient, job_id: str, timeout_s: float = 600) -> dict:
    end = time.monotonic() + timeout_s
    while time.monotonic() < end:
        state = c.get(f"/jobs/{job_id}").json()
        if state["status"] not in ("queued", "running"):
            return state
        time.sleep(0.1)
    raise AssertionError(f"job {job_id} did not end")


def test_auto_reaches_the_budget_with_planned_poses_and_a_true_hand_eye(service) -> None:
    c, _ = service
    sid, config = _arm_rig(c, 1)
    truth = SimulatorTruth.from_config(config).handeye()
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
    c, _ = service
    sid, _ = _arm_rig(c, 2)
    job = _wait(c, _start(c, sid, target={"worst_ray_sigma_urad": 1e6,
                                          "handeye_sigma_mm": 100}))
    assert job["status"] == "succeeded", job
    log = job["result"]
    assert log["stop_reason"] == "target met" and len(log["poses"]) == 4
    assert log["handeye"]["sigma"]["translation_mm"] <= 100


def test_poses_the_mover_cannot_reach_are_skipped_and_the_next_best_taken(service) -> None:
    c, _ = service
    sid, config = _arm_rig(c, 3, reach_mm=120.0)
    truth = SimulatorTruth.from_config(config).handeye()
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
    sid, _ = _arm_rig(c, 4, speed_mm_s=1000.0, speed_deg_s=0.5)  # a turn takes a minute
    rig_id = c.get(f"/sessions/{sid}").json()["rig_id"]
    job_id = _start(c, sid)
    end = time.monotonic() + 120
    while "pose 3/6: moving" not in c.get(f"/jobs/{job_id}").json()["stage"]:
        assert time.monotonic() < end, "the first turn never started"
        time.sleep(0.05)
    moving = c.get(f"/sessions/{sid}/auto").json()["moving_to"]
    assert moving["reason"].startswith("starting set: turn")  # the planned pose, while moving
    time.sleep(0.3)
    assert c.post(f"/jobs/{job_id}/cancel").status_code in (200, 202)
    job = _wait(c, job_id)
    assert job["status"] == "cancelled", job
    arm = svc.rigs.handle(rig_id).rig.mover
    assert arm.moves == 2  # where it stood and the step back; the first turn stopped midway
    log = c.get(f"/sessions/{sid}/auto").json()
    assert log["stop_reason"] == "cancelled" and log["moving_to"] == moving  # where it went
    target = RobotPose.from_json(log["poses"][0]["flange"])
    assert 0 < arm.current_pose().angle_to_deg(target) < 29  # stopped part of the way
    poses = c.get(f"/sessions/{sid}/poses").json()
    assert [p["status"] for p in poses] == ["ready", "ready"]
    assert log["poses"][0]["pose_id"] == poses[0]["id"]


def test_cli_auto_writes_poses_handeye_and_log(tmp_path: Path, monkeypatch, capsys) -> None:
    rig_toml = tmp_path / "rig.toml"
    rig_toml.write_text('kind = "simulated"\ncamera = {width = 160, height = 120}\n'
                        '[mover]\nbackend = "simulated-arm"\nspeed_mm_s = 20000\n'
                        'speed_deg_s = 5000\nsettle_s = 0\n')
    out = tmp_path / "run"
    assert main(["auto", "--rig", str(rig_toml), "--target-sigma-urad", "1e6",
                 "--handeye-sigma-mm", "100", "--budget", "5", "-o", str(out)]) == 0
    printed = capsys.readouterr().out
    assert "stopped: target met" in printed and "hand-eye t_mm" in printed
    log = json.loads((out / "auto.json").read_text())
    assert [p["pose_id"] for p in log["poses"]] == [f"pose-{k:02d}" for k in range(4)]
    assert all((out / f"pose-{k:02d}" / "maps.npz").is_file() for k in range(4))
    handeye = json.loads((out / "handeye.json").read_text())
    assert handeye["format"] == "phasecal.handeye/1"
    truth = SimulatorTruth.from_config(tomllib.loads(rig_toml.read_text())).handeye()
    error = np.linalg.norm(np.asarray(handeye["hand_eye"]["t_mm"]) - truth.hand_eye.translation_mm)
    assert error < 5 * handeye["stats"]["hand_eye_sigma"]["translation_mm"]
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


def test_a_starting_turn_that_lost_the_screen_is_dropped_and_the_next_taken(
        tmp_path: Path) -> None:
    rig = open_rig(parse_rig_config(RIG), simulator=open_simulated_rig)
    taken: list[str] = []

    def capture(ctx: TaskContext) -> str:  # the first turn's capture decodes nothing
        maps = perfect_maps(rig.simulated)
        if len(taken) == 2:
            maps.mask[:] = False
        taken.append(f"pose-{len(taken)}")
        save_maps(maps, tmp_path / f"{taken[-1]}.npz")
        return taken[-1]

    def refit(ctx: TaskContext, robot: dict[str, Any]) -> dict[str, Any]:
        return {"worst_ray_sigma_urad": 1.0, "handeye": None, "handeye_sigma": None,
                "note": "", "candidates": []}

    loop = AutoLoop(rig, "eye-in-hand", "opencv5", 6, 10.0, capture, refit, lambda log: None,
                    lambda name: tmp_path / f"{name}.npz")
    log = loop.run(TaskContext("auto"))
    rig.close()
    assert [p["pose_id"] for p in log["poses"]] == ["pose-0", "pose-1", "pose-3", "pose-4"]
    assert [s["pose_id"] for s in log["skipped"]] == ["pose-2"]
    assert "lost the screen" in log["skipped"][0]["why"]
    assert log["stop_reason"] == "target met"
