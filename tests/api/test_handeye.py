"""`phasecal handeye` and POST /sessions/{id}/handeye end to end on a simulated arm: maps and
observations in, phasecal.handeye/1 out, against the arm's truth; refusals."""

from __future__ import annotations

import json
import time
from pathlib import Path

import numpy as np
import pytest
from fastapi.testclient import TestClient

from acquisition.patterns import build_plan
from api.app import create_app
from api.cli import main
from api.config import ServiceConfig
from calibration.handeye.rigid import Rigid
from calibration.shared.maps import save_maps
from calibration.shared.observations import TargetObservations, save_observations
from calibration.shared.plan import write_plan
from hw_mocks.arm import HandEyeRig, handeye_rig
from hw_mocks.cameras import mild_pinhole
from hw_mocks.synthetic import synthetic_maps

PLAN = build_plan(320, 180, 1.0, preset="fast")
CAMERA = mild_pinhole(160, 120)
VIEWS = 6


def _truth_sigma(doc: dict, rig: HandEyeRig) -> np.ndarray:
    """The hand-eye's error against the rig's truth in units of its stated sigma."""
    got = Rigid(np.array(doc["hand_eye"]["R"]), np.array(doc["hand_eye"]["t_mm"]))
    err = got.minus(Rigid(rig.hand_eye.rotation, rig.hand_eye.translation_mm))
    return err / np.sqrt(np.diag(doc["hand_eye"]["covariance"]))


@pytest.fixture(scope="module")
def recorded(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, HandEyeRig]:
    """An eye-in-hand run: per view maps.npz, observations of a 9x6 grid of screen points
    (0.1 px noise) and the robot's reported poses in robot.json."""
    d = tmp_path_factory.mktemp("handeye")
    write_plan(PLAN, d / "plan.json")
    rng = np.random.default_rng(5)
    rig = handeye_rig("eye-in-hand", CAMERA, PLAN.screen, rng, speed_mm_s=1e6,
                      speed_deg_s=1e6, settle_s=0.0)
    gx, gy = np.meshgrid(np.linspace(20, 300, 9), np.linspace(15, 165, 6))
    grid = np.stack([gx.ravel(), gy.ravel(), np.zeros(gx.size)], 1)
    poses = {}
    for k, flange in enumerate(rig.view_plan(VIEWS, rng)):
        poses[f"v{k}"] = rig.arm.move_to(flange, 1.0).to_json()
        seen = rig.screen_pose()
        maps, _ = synthetic_maps(CAMERA, seen, PLAN.screen, sigma_px=0.05, rng=rng,
                                 pose_id=f"v{k}")
        maps.meta["plan_digest"] = PLAN.digest()
        save_maps(maps, d / f"v{k}.npz")
        xy = CAMERA.project(seen.screen_to_camera(grid)) + 0.1 * rng.standard_normal((54, 2))
        save_observations(TargetObservations(xy, grid, (CAMERA.width, CAMERA.height),
                                             sigma_px=0.1), d / f"v{k}.obs.npz")
    robot = {"format": "phasecal.robot-poses/1", "poses": poses,
             "repeatability": {"mm": 0.02, "deg": 0.005}}
    (d / "robot.json").write_text(json.dumps(robot))
    return d, rig


def _cli(d: Path, *extra: str) -> list[str]:
    return ["handeye", "--mount", "eye-in-hand", "--robot-poses", str(d / "robot.json"),
            "--model", "opencv5", *extra]


@pytest.mark.parametrize("source", ["maps", "observations"])
def test_cli_handeye_recovers_the_arm_truth(recorded, source: str, capsys) -> None:
    d, rig = recorded
    suffix = ".npz" if source == "maps" else ".obs.npz"
    out = d / f"handeye-{source}.json"
    files = [f"v{k}={d / f'v{k}{suffix}'}" for k in range(VIEWS)]
    assert main(_cli(d, "--plan", str(d / "plan.json"), f"--{source}", *files,
                     "-o", str(out))) == 0
    assert "held out: RMS" in capsys.readouterr().out
    doc = json.loads(out.read_text())
    assert doc["format"] == "phasecal.handeye/1" and doc["mount"] == "eye-in-hand"
    assert doc["camera"]["format"] == "phasecal.model/1"
    assert np.all(np.abs(_truth_sigma(doc, rig)) < 3)
    assert len(doc["heldout"]["views"]) == VIEWS


def test_cli_handeye_refusals_are_one_line(recorded, capsys) -> None:
    d, _ = recorded
    maps = [f"v{k}={d / f'v{k}.npz'}" for k in range(VIEWS)]
    cases = [
        (_cli(d, "--maps", *maps, "-o", str(d / "x.json")), "--plan"),
        (_cli(d, "--plan", str(d / "plan.json"), "--maps", str(d / "v0.npz"), "-o",
              str(d / "x.json")), "VIEW=PATH"),
        (_cli(d, "--plan", str(d / "plan.json"), "--maps", *maps, f"extra={d / 'v0.npz'}",
              "-o", str(d / "x.json")), "no pose for view(s) extra"),
    ]
    for argv, needle in cases:
        assert main(argv) == 1
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and needle in err[0], err
    assert not (d / "x.json").exists()


def _wait(c: TestClient, job: dict) -> dict:
    for _ in range(1200):
        state = c.get(f"/jobs/{job['id']}").json()
        if state["status"] not in ("queued", "running"):
            return state
        time.sleep(0.05)
    raise AssertionError(f"job {job['id']} did not end")


def test_rest_handeye_on_session_poses(recorded, tmp_path: Path) -> None:
    d, rig = recorded
    robot = json.loads((d / "robot.json").read_text())
    app = create_app(ServiceConfig(data_dir=tmp_path / "data", executor="threads"))
    with TestClient(app) as c:
        sid = c.post("/sessions", json={"plan": PLAN.to_dict()}).json()["id"]
        assert c.get(f"/sessions/{sid}/handeye").status_code == 404
        by_pose = {}
        for k in range(VIEWS):
            r = c.post(f"/sessions/{sid}/poses/import-maps",
                       files={"file": ("maps.npz", (d / f"v{k}.npz").read_bytes())})
            assert r.status_code == 201, r.text
            by_pose[r.json()["id"]] = robot["poses"][f"v{k}"]
        body = {"mount": "eye-in-hand", "model": "opencv5",
                "robot_poses": {**robot, "poses": by_pose}}
        bad = c.post(f"/sessions/{sid}/handeye", json={**body, "robot_poses": {
            **robot, "repeatability": {"mm": 0.02}}})
        assert bad.status_code == 422 and "robot_poses: repeatability" in bad.json()["detail"]
        stranger = c.post(f"/sessions/{sid}/handeye", json={**body, "robot_poses": {
            **robot, "poses": {**by_pose, "pose_nosuch": robot["poses"]["v0"]}}})
        assert stranger.status_code == 422 and "pose_nosuch" in stranger.json()["detail"]
        few = dict(list(by_pose.items())[:3])
        r = c.post(f"/sessions/{sid}/handeye", json={**body, "robot_poses": {**robot,
                                                                           "poses": few}})
        assert r.status_code == 409 and r.json()["detail"].startswith("hand-eye needs >= 4")
        r = c.post(f"/sessions/{sid}/handeye", json=body)
        assert r.status_code == 202, r.text
        final = _wait(c, r.json())
        assert final["status"] == "succeeded", final.get("error")
        doc = c.get(f"/sessions/{sid}/handeye").json()
        assert doc["format"] == "phasecal.handeye/1"
        assert sorted(doc["stats"]["views"]) == sorted(by_pose)
        assert np.all(np.abs(_truth_sigma(doc, rig)) < 3)


def test_rest_handeye_on_target_session_views(recorded, tmp_path: Path) -> None:
    """Observation files uploaded as a target session's views, the robot poses keyed by the
    view ids: the same hand-eye, read back from the target session."""
    d, rig = recorded
    robot = json.loads((d / "robot.json").read_text())
    app = create_app(ServiceConfig(data_dir=tmp_path / "data", executor="threads"))
    with TestClient(app) as c:
        sid = c.post("/target-sessions", json={"name": "arm", "target": "points"}).json()["id"]
        by_view = {}
        for k in range(VIEWS):
            r = c.post(f"/target-sessions/{sid}/views",
                       files={"file": (f"v{k}.npz", (d / f"v{k}.obs.npz").read_bytes())})
            assert r.status_code == 201, r.text
            by_view[r.json()["id"]] = robot["poses"][f"v{k}"]
        body = {"mount": "eye-in-hand", "model": "opencv5",
                "robot_poses": {**robot, "poses": by_view}}
        stranger = c.post(f"/target-sessions/{sid}/handeye", json={**body, "robot_poses": {
            **robot, "poses": {**by_view, "pose_nosuch": robot["poses"]["v0"]}}})
        assert stranger.status_code == 422 and "pose_nosuch" in stranger.json()["detail"]
        r = c.post(f"/target-sessions/{sid}/handeye", json=body)
        assert r.status_code == 202, r.text
        final = _wait(c, r.json())
        assert final["status"] == "succeeded", final.get("error")
        doc = c.get(f"/target-sessions/{sid}/handeye").json()
        assert sorted(doc["stats"]["views"]) == sorted(by_view)
        assert np.all(np.abs(_truth_sigma(doc, rig)) < 3)
