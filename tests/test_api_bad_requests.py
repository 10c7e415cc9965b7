"""Requests that answered 500 (or were silently accepted) are 4xx problems now."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from fastapi.testclient import TestClient

from api.app import create_app
from api.config import ServiceConfig
from tests.test_api_uploads import PLAN, good_maps


@pytest.fixture(scope="module")
def client(tmp_path_factory: pytest.TempPathFactory):
    data = tmp_path_factory.mktemp("bad") / "data"
    app = create_app(ServiceConfig(data_dir=data, executor="threads"))
    with TestClient(app, raise_server_exceptions=False) as c:
        yield c


def _problem(r, status: int = 422) -> dict:
    assert r.status_code == status, r.text
    assert r.headers["content-type"].startswith("application/problem+json")
    return r.json()


@pytest.mark.parametrize("path", ["/sessions", "/jobs", "/calibrations"])
def test_huge_offsets(client: TestClient, path: str) -> None:
    body = _problem(client.get(path, params={"offset": "9223372036854775808"}))
    assert "offset" in body["detail"]
    assert client.get(path, params={"offset": 5}).status_code == 200


def test_non_finite_and_non_numbers_in_bodies(client: TestClient) -> None:
    rig = client.get("/rigs").json()[0]["id"]
    nan_pose = '{"rvec": [NaN, 0, 0], "tvec_mm": [0, 0, 300]}'
    r = client.put(f"/rigs/{rig}/screen-pose", content=nan_pose,
                   headers={"content-type": "application/json"})
    assert "rvec.0" in _problem(r)["detail"]
    sess = client.post("/sessions", json={"preset": "fast"}).json()
    r = client.post(f"/sessions/{sess['id']}/poses", content='{"screen_pose": ' + nan_pose + "}",
                    headers={"content-type": "application/json"})
    _problem(r)
    r = client.put(f"/rigs/{rig}/screen-pose", json={"rvec": [False, 0, 0], "tvec_mm": [0, 0, 1]})
    _problem(r)
    r = client.put(f"/rigs/{rig}/camera/settings", json={"exposure_s": True})
    assert "exposure_s" in _problem(r)["detail"]
    r = client.put(f"/rigs/{rig}/screen-pose", json={"rvec": [0, 0, 0], "tvec_mm": [0, 0, 1e300]})
    _problem(r)


def test_zero_pitch_is_refused(client: TestClient) -> None:
    for pitch in (0, [0.25, 0.0], -1):
        r = client.post("/rigs", json={"name": "p", "config": {"screen": {"pitch_mm": pitch}}})
        assert "screen.pitch_mm" in _problem(r)["detail"]


def test_project_camera_centre_on_sgcc_is_a_null_row(client: TestClient) -> None:
    sess = client.post("/sessions", json={"plan": PLAN.to_dict()}).json()
    for k in range(3):
        r = client.post(f"/sessions/{sess['id']}/poses/import-maps",
                        files={"file": ("m.npz", good_maps(10 + k, size=(160, 120))
                                        .to_npz_bytes())})
        assert r.status_code == 201, r.text
    job = client.post(f"/sessions/{sess['id']}/calibrations", json={"model": "sgcc"}).json()
    while job["status"] in ("queued", "running"):
        job = client.get(f"/jobs/{job['id']}").json()
    assert job["status"] == "succeeded", job["error"]
    cal = job["resource"]
    r = client.post(f"{cal}/project", json={"points": [[0, 0, 0], [0, 0, 500.0]]})
    assert r.status_code == 200, r.text
    pixels = r.json()["pixels"]
    assert pixels[0] == [None, None]
    assert np.isfinite(np.asarray(pixels[1], float)).all()
    _problem(client.post(f"{cal}/project", json={"points": [[False, 0, 1]]}))
    _problem(client.post(f"{cal}/unproject", json={"pixels": [["1", 2]]}))


def test_health_hides_the_data_dir_without_a_token(tmp_path: Path) -> None:
    app = create_app(ServiceConfig(data_dir=tmp_path / "d", executor="threads", token="s3cret"))
    with TestClient(app) as c:
        open_body = c.get("/health").json()
        assert open_body["status"] == "ok" and "data_dir" not in open_body
        assert str(tmp_path) not in c.get("/health").text
        authed = c.get("/health", headers={"Authorization": "Bearer s3cret"}).json()
        assert authed["data_dir"] == str((tmp_path / "d").resolve())


def test_token_from_a_file_or_the_environment(tmp_path: Path,
                                              monkeypatch: pytest.MonkeyPatch) -> None:
    from api.config import ServiceConfig as Cfg

    f = tmp_path / "token"
    f.write_text("  from-file\n")
    monkeypatch.delenv("PHASECAL_TOKEN", raising=False)
    monkeypatch.setenv("PHASECAL_TOKEN_FILE", str(f))
    assert Cfg.from_env().token == "from-file"
    monkeypatch.setenv("PHASECAL_TOKEN", "from-env")
    assert Cfg.from_env().token == "from-env"
    f.write_text("\n")
    monkeypatch.delenv("PHASECAL_TOKEN")
    with pytest.raises(ValueError, match="empty"):
        Cfg.from_env()
