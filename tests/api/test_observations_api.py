"""Target sessions over REST: images detected server-side and observation files uploaded,
bad uploads refused before anything is stored, calibrations of the views (pixel space)."""

from __future__ import annotations

from pathlib import Path

import pytest
from fastapi.testclient import TestClient

from api.app import create_app
from api.config import ServiceConfig
from calibration.shared.observations import load_observations
from tests.calibration.targets.conftest import SAMPLE_SPEC, sample_images


@pytest.fixture(scope="module")
def client(tmp_path_factory):
    data = tmp_path_factory.mktemp("obs") / "data"
    app = create_app(ServiceConfig(data_dir=data, executor="threads", max_upload_bytes=1 << 20))
    with TestClient(app) as c:
        yield c


def _upload(client, sid: str, path: Path, name: str | None = None):
    return client.post(f"/target-sessions/{sid}/views",
                       files={"file": (name or path.name, path.read_bytes())})


def test_board_session_images_and_calibration(client, tmp_path):
    r = client.post("/target-sessions", json={"name": "left", "target": SAMPLE_SPEC})
    assert r.status_code == 201, r.text
    sid = r.json()["id"]
    images = sample_images("left")
    for img in images[:-1]:
        r = _upload(client, sid, img)
        assert r.status_code == 201, r.text
        assert r.json()["source"] == "image" and r.json()["points"] == 54
    # the last view as an observations file (downloaded from a view detected here)
    vid = client.get(f"/target-sessions/{sid}/views").json()[0]["id"]
    npz = client.get(f"/target-sessions/{sid}/views/{vid}/observations.npz")
    assert npz.status_code == 200
    (tmp_path / "v.npz").write_bytes(npz.content)
    assert load_observations(tmp_path / "v.npz").used_count() == 54
    r = _upload(client, sid, images[-1])
    assert r.status_code == 201
    assert client.get(f"/target-sessions/{sid}").json()["views"] == 13
    r = client.post(f"/target-sessions/{sid}/calibrations",
                    json={"model": "opencv5", "options": {"target": "fit"}, "cross_validate": 2})
    assert r.status_code == 201, r.text
    cal = r.json()
    assert cal["stats"]["cross_validation"]["verdict"] == "agree"
    assert cal["stats"]["target"]["mode"] == "fit" and len(cal["view_ids"]) == 13
    model = client.get(f"/target-sessions/{sid}/calibrations/{cal['id']}/model.json").json()
    assert model["type"] == "opencv5" and model["image_size"] == [640, 480]
    assert client.get(f"/target-sessions/{sid}/calibrations/{cal['id']}").json()["id"] == cal["id"]
    for name in ("residuals", "uncertainty"):
        png = client.get(f"/target-sessions/{sid}/calibrations/{cal['id']}/{name}.png")
        assert png.status_code == 200 and png.content[:4] == b"\x89PNG"
    r = client.post(f"/target-sessions/{sid}/calibrations",
                    json={"model": "sgcc", "options": {"target": "fit", "cells": [6, 5]}})
    assert r.status_code == 201, r.text
    generic = r.json()
    assert generic["stats"]["mesh"]["candidates"][0]["cells"] == [6, 5]
    assert generic["stats"]["rms_px"] <= cal["stats"]["rms_px"]
    model = client.get(f"/target-sessions/{sid}/calibrations/{generic['id']}/model.json").json()
    assert model["type"] == "sgcc" and model["params"]["cells"] == [6, 5]


def test_bad_uploads_and_requests_are_refused(client, tmp_path):
    sid = client.post("/target-sessions", json={"target": SAMPLE_SPEC}).json()["id"]
    bad = tmp_path / "bad.png"
    bad.write_bytes(b"\x89PNG not really")
    r = _upload(client, sid, bad)
    assert r.status_code == 422 and "bad.png: neither an observations NPZ" in r.json()["detail"]
    blank = sample_images("left")[0].read_bytes()[:2000]  # a truncated JPEG
    r = client.post(f"/target-sessions/{sid}/views", files={"file": ("cut.jpg", blank)})
    assert r.status_code == 422
    other = client.post("/target-sessions", json={"target": "chessboard:7x5:30"}).json()["id"]
    r = _upload(client, other, sample_images("right")[3])
    assert r.status_code == 201  # a 7x5 part of the 9x6 board: consistent, if not all of it
    vid = r.json()["id"]
    npz = client.get(f"/target-sessions/{other}/views/{vid}/observations.npz").content
    r = client.post(f"/target-sessions/{sid}/views", files={"file": ("v.npz", npz)})
    assert r.status_code == 422 and "target_xyz: not the points" in r.json()["detail"]
    assert client.get(f"/target-sessions/{sid}").json()["views"] == 0
    pts = client.post("/target-sessions", json={"target": "points"}).json()["id"]
    r = _upload(client, pts, sample_images("left")[0])
    assert r.status_code == 422 and "surveyed points" in r.json()["detail"]
    r = client.post(f"/target-sessions/{pts}/views", files={"file": ("v.npz", npz)})
    assert r.status_code == 201
    for body, message in [
        ({"model": "raygrid"}, "raygrid cannot be fitted to target observations"),
        ({"model": "sgcc"}, "sgcc needs >= 3 views, got 1"),
        ({"model": "opencv5", "options": {"outlier_sigma": 0}}, "options.outlier_sigma"),
        ({"model": "opencv5"}, "needs >= 3 views"),
        ({"model": "opencv5", "view_ids": ["pose_0000000000000000"]}, "view_ids: not views"),
    ]:
        r = client.post(f"/target-sessions/{pts}/calibrations", json=body)
        assert r.status_code == 422 and message in r.json()["detail"], r.text
    r = client.post("/target-sessions", json={"target": "chessboard:9x6"})
    assert r.status_code == 422 and r.json()["detail"].startswith("target: target")
    assert client.get("/target-sessions/ses_0123456789abcdef").status_code == 404
