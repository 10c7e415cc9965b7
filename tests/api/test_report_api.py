"""Calibration reports and model diffs over HTTP and from the CLI, on the simulated rig.

Every image of the report must exist, decode and show something, and the page must be
reproducible from the stored files alone: `phasecal report` run on the downloaded model,
result and maps gives the same numbers.
"""

from __future__ import annotations

import io
import json
import re
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from api.cli import main
from api.client import PhasecalClient, ServiceError
from api.config import ServiceConfig
from api.inprocess import running_service
from calibration.evaluate import pose_residuals
from calibration.fit.correspondences import point_set, subsample
from calibration.fit.result import PoseEstimate
from calibration.models.base import model_from_dict
from calibration.shared.maps import load_maps
from calibration.shared.plan import plan_from_dict
from tests.api.test_api_session import screen_poses, small_rig

EXPECTED = ("histogram.png", "radial.png", "uncertainty.png", "coverage.png", "pose_00.png",
            "pose_01.png", "pose_02.png", "heldout_03.png")


@pytest.fixture(scope="module")
def service(tmp_path_factory: pytest.TempPathFactory):
    root = tmp_path_factory.mktemp("report")
    with running_service(ServiceConfig(data_dir=root / "data")) as (url, _app):
        client = PhasecalClient(url)
        rig = client.post("/rigs", {"name": "small", "config": small_rig()})
        ses = client.post("/sessions", {"name": "r", "rig_id": rig["id"], "preset": "fast"})
        poses = []
        for pose in screen_poses(4, seed=11):
            job = client.wait(client.post(f"/sessions/{ses['id']}/poses", {"screen_pose": pose}))
            assert job["status"] == "succeeded", job
            poses.append(job["resource"].rsplit("/", 1)[-1])
        cals = {}
        for model, opts in (("opencv5", {}), ("sgcc", {"cells": [4, 3]})):
            job = client.wait(client.post(f"/sessions/{ses['id']}/calibrations",
                                          {"model": model, "pose_ids": poses[:3],
                                           "heldout_pose_ids": poses[3:], "options": opts}))
            assert job["status"] == "succeeded", job
            cals[model] = job["resource"].rsplit("/", 1)[-1]
        yield client, ses, poses, cals, root
        client.close()


def _png(data: bytes) -> np.ndarray:
    img = np.asarray(Image.open(io.BytesIO(data)).convert("L"), dtype=np.float64)
    assert img.shape[0] > 100 and img.shape[1] > 100
    assert img.std() > 10, "a blank image"
    return img


@pytest.mark.parametrize("model", ["opencv5", "sgcc"])
def test_report_has_every_view_drawn_from_stored_data(service, model, tmp_path: Path) -> None:
    client, ses, poses, cals, _ = service
    cal_id = cals[model]
    page = client.request("GET", f"/calibrations/{cal_id}/report.html").text
    images = re.findall(r'src="report/([a-z_0-9]+\.png)"', page)
    assert sorted(images) == sorted(EXPECTED), images
    for name in images:
        r = client.request("GET", f"/calibrations/{cal_id}/report/{name}")
        assert r.headers["content-type"] == "image/png"
        _png(r.content)
    assert "ray 1-sigma max (urad)" in page and "held-out" in page
    other = cals["sgcc" if model == "opencv5" else "opencv5"]
    assert f"/calibrations/{cal_id}/diff/{other}/diff.png" in page

    # The same numbers from the stored files alone, through the CLI.
    files = {}
    for name in ("model.json", "result.json"):
        files[name] = tmp_path / name
        files[name].write_bytes(client.request("GET", f"/calibrations/{cal_id}/files/{name}")
                                .content)
    plan = tmp_path / "plan.json"
    plan.write_text(json.dumps(client.get(f"/sessions/{ses['id']}/plan")))
    maps = []
    for pid in poses:
        path = tmp_path / f"{pid}.npz"
        path.write_bytes(client.request(
            "GET", f"/sessions/{ses['id']}/poses/{pid}/maps.npz").content)
        maps.append(path)
    out = tmp_path / "cli"
    assert main(["report", "--model", str(files["model.json"]), "--plan", str(plan),
                 "--result", str(files["result.json"]), "--maps", *map(str, maps[:3]),
                 "--heldout-maps", str(maps[3]), "-o", str(out)]) == 0
    cli_page = (out / "report.html").read_text()
    table = re.compile(r"<table>.*?</table>", re.S)
    assert table.findall(cli_page)[:2] == table.findall(page)[:2]
    assert sorted(p.name for p in out.glob("*.png")) == sorted(EXPECTED)

    # The per-pose RMS in the page is the residual of the stored model, pose and maps.
    model_obj = model_from_dict(json.loads(files["model.json"].read_text()))
    result = json.loads(files["result.json"].read_text())
    screen = plan_from_dict(json.loads(plan.read_text())).screen
    pose = result["poses"][0]
    pts = subsample(point_set(load_maps(maps[0]), screen), 6000)
    st = pose_residuals(model_obj, PoseEstimate(np.array(pose["rotation"]),
                                                np.array(pose["translation_mm"])), pts)
    assert f"<td>{poses[0]}</td><td>{st['rms_px']:.4g}</td>" in page


def test_diff_between_two_calibrations(service, tmp_path: Path) -> None:
    client, ses, poses, cals, _ = service
    a, b = cals["opencv5"], cals["sgcc"]
    d = client.get(f"/calibrations/{a}/diff/{b}")
    assert 0 < d["rms_urad"] <= d["max_urad"] and d["pixels_compared"] > 100
    _png(client.request("GET", d["image"]).content)
    with pytest.raises(ServiceError) as err:
        client.get(f"/calibrations/{a}/diff/{a}")
    assert err.value.status == 422
    files = []
    for cid in (a, b):
        path = tmp_path / f"{cid}.json"
        path.write_bytes(client.request("GET", f"/calibrations/{cid}/files/model.json").content)
        files.append(str(path))
    maps = []
    for pid in poses[:3]:  # the poses both calibrations used: the pixels the API compares
        path = tmp_path / f"{pid}.npz"
        path.write_bytes(client.request(
            "GET", f"/sessions/{ses['id']}/poses/{pid}/maps.npz").content)
        maps.append(str(path))
    assert main(["diff", *files, "--maps", *maps, "-o", str(tmp_path / "d")]) == 0
    assert (tmp_path / "d" / "diff.png").is_file()
    summary = json.loads((tmp_path / "d" / "diff.json").read_text())
    assert summary["pixels_compared"] == d["pixels_compared"]
    assert summary["rms_urad"] == pytest.approx(d["rms_urad"], rel=1e-9)


def test_decode_previews_have_colour_bars(service) -> None:
    client, ses, poses, _, _ = service
    for kind in ("x", "y", "sigma", "mask"):
        img = _png(client.request(
            "GET", f"/sessions/{ses['id']}/poses/{poses[0]}/preview/{kind}.png").content)
        assert img.shape[1] > 400  # map plus colour bar, not the bare 160 px map


def test_next_pose_is_visible_and_captures(service) -> None:
    client, ses, poses, _, _ = service
    g = client.get(f"/sessions/{ses['id']}/next-pose", model="opencv5")
    assert g["poses_used"] == poses and g["full_screen_visible"]
    pred = g["predicted_worst_ray_sigma_urad"]
    assert 0 < pred["after"] < pred["now"]
    _png(client.request("GET", g["image"]).content)
    # The simulator's truth (from outside the product) sees the whole screen there.
    from hw_mocks.scene import ScreenPose
    from tests.api.test_api_session import SCREEN, truth_camera

    pose = ScreenPose.from_rvec(np.array(g["screen_pose"]["rvec"]),
                                np.array(g["screen_pose"]["tvec_mm"]))
    cam = truth_camera()
    corners = np.array([[0, 0], [SCREEN.width_px - 1, 0], [0, SCREEN.height_px - 1],
                        [SCREEN.width_px - 1, SCREEN.height_px - 1]], float)
    px = cam.project(pose.screen_px_to_camera(SCREEN, corners[:, 0], corners[:, 1]))
    assert np.all((px >= 0) & (px <= [cam.width - 1, cam.height - 1]))
    job = client.wait(client.post(f"/sessions/{ses['id']}/poses",
                                  {"screen_pose": g["screen_pose"]}))
    assert job["status"] == "succeeded"
    info = client.get(job["resource"])
    assert info["valid_pixels"] > 0.5 * g["image_fraction"] * 160 * 120
