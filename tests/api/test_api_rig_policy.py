"""Rigs created over REST name only listed devices and recordings inside the data directory."""

from __future__ import annotations

import os
from pathlib import Path

import pytest
from fastapi.testclient import TestClient

from acquisition.rig import parse_rig_config
from api.app import create_app
from api.config import ServiceConfig
from api.problems import Problem
from api.rig_policy import check_client_rig


def _hw(display: dict, camera: dict) -> dict:
    return {"kind": "hardware", "screen": {"pitch_mm": 0.25}, "display": display,
            "camera": camera}


SDL = {"backend": "sdl", "video_driver": "dummy", "width": 64, "height": 48}
FB_GEOMETRY = {"width": 16, "height": 16, "bits_per_pixel": 32}


@pytest.fixture()
def app_client(tmp_path: Path):
    app = create_app(ServiceConfig(data_dir=tmp_path / "data", executor="threads"))
    with TestClient(app) as c:
        yield c


def _refused(c: TestClient, config: dict, field: str) -> dict:
    r = c.post("/rigs", json={"name": "client", "config": config})
    assert r.status_code == 422, r.text
    body = r.json()
    assert r.headers["content-type"].startswith("application/problem+json")
    assert body["detail"].startswith(field + ":") and body["field"] == field
    return body


def test_framebuffer_device_that_is_an_ordinary_file_is_refused(app_client, tmp_path) -> None:
    victim = tmp_path / "victim.bin"
    victim.write_bytes(b"precious" * 4096)
    cfg = _hw({"backend": "framebuffer", "device": str(victim), **FB_GEOMETRY},
              {"backend": "opencv", "source": 0})
    _refused(app_client, cfg, "config.display.device")
    # a capture on such a rig wrote pattern pixels into the file: nothing touched it now
    assert victim.read_bytes() == b"precious" * 4096
    assert [r["name"] for r in app_client.get("/rigs").json()] == ["default"]
    sysfs = _hw({"backend": "framebuffer", "device": "/dev/fb0", "sysfs_root": str(tmp_path),
                 **FB_GEOMETRY}, {"backend": "opencv", "source": 0})
    _refused(app_client, sysfs, "config.display.sysfs_root")


@pytest.mark.parametrize("source", ["/etc/hostname.mkv", "../outside.mkv",
                                    "recordings/../../x.mkv", "/etc/passwd", "http://x/y.mkv",
                                    "/dev/sda", 7])
def test_camera_sources_outside_the_data_dir_are_refused(app_client, source) -> None:
    _refused(app_client, _hw(SDL, {"backend": "opencv", "source": source}),
             "config.camera.source")


def test_symlink_leading_out_of_the_data_dir_is_refused(app_client, tmp_path) -> None:
    outside = tmp_path / "elsewhere"
    outside.mkdir()
    (outside / "clip.mkv").write_bytes(b"")
    (outside / "frame_0000.png").write_bytes(b"")
    rec = tmp_path / "data" / "recordings"
    rec.mkdir()
    os.symlink(outside / "clip.mkv", rec / "clip.mkv")
    os.symlink(outside, rec / "linked")
    seq = tmp_path / "data" / "seq"
    seq.mkdir()
    os.symlink(outside / "frame_0000.png", seq / "frame_0000.png")
    for source in ("recordings/clip.mkv", str(rec / "clip.mkv"), "recordings/linked/clip.mkv",
                   "seq/frame_%04d.png"):
        _refused(app_client, _hw(SDL, {"backend": "opencv", "source": source}),
                 "config.camera.source")


def test_aravis_device_must_be_listed(app_client) -> None:
    _refused(app_client, _hw(SDL, {"backend": "aravis", "device": "10.0.0.1"}),
             "config.camera.device")


def test_recordings_inside_the_data_dir_and_listed_devices_pass(tmp_path) -> None:
    data = tmp_path / "data"
    (data / "rec").mkdir(parents=True)
    cfg = parse_rig_config(_hw(SDL, {"backend": "opencv", "source": "rec/frame_%04d.png"}))
    out = check_client_rig(cfg, data)
    assert out.camera.source == str((data / "rec").resolve() / "frame_%04d.png")
    dev = tmp_path / "dev"
    dev.mkdir()
    (dev / "fb0").write_bytes(b"")
    (dev / "video2").write_bytes(b"")
    fb = str(dev / "fb0")
    cfg = parse_rig_config(_hw({"backend": "framebuffer", "device": fb, **FB_GEOMETRY},
                               {"backend": "opencv", "source": 2}))
    out = check_client_rig(cfg, data, dev_root=dev, sysfs_root=tmp_path / "sys")
    assert out.display.device == fb and out.camera.source == 2
    aravis = parse_rig_config(_hw(SDL, {"backend": "aravis", "device": "127.0.0.1"}))
    assert check_client_rig(aravis, data, aravis_ids=("127.0.0.1",)).camera.device == "127.0.0.1"
    with pytest.raises(Problem, match=r"config\.camera\.source"):
        check_client_rig(parse_rig_config(_hw(SDL, {"backend": "opencv", "source": 3})), data,
                         dev_root=dev)


def test_operator_rigs_folder_may_name_any_path(tmp_path) -> None:
    rigs = tmp_path / "rigs"
    rigs.mkdir()
    (rigs / "bench.toml").write_text(
        'kind = "hardware"\n[screen]\npitch_mm = 0.25\n'
        '[display]\nbackend = "framebuffer"\ndevice = "/tmp/fb-test"\nwidth = 16\nheight = 16\n'
        '[camera]\nbackend = "opencv"\nsource = "/srv/recordings/clip.mkv"\n')
    app = create_app(ServiceConfig(data_dir=tmp_path / "data", executor="threads",
                                   rigs_dir=rigs))
    with TestClient(app) as c:
        listed = {r["name"]: r for r in c.get("/rigs").json()}
        assert listed["bench"]["config"]["display"]["device"] == "/tmp/fb-test"
        r = c.post("/rigs", json={"name": "bench", "config": {"kind": "simulated"}})
        assert r.status_code == 409


@pytest.mark.parametrize(("camera", "field"), [
    ({"width": 100_000, "height": 100_000}, "config.camera.width"),
    ({"supersample": 64}, "config.camera.supersample"),
    ({"width": "160"}, "config.camera.width"),
])
def test_simulated_rigs_over_rest_are_bounded(app_client, camera, field) -> None:
    _refused_size = app_client.post("/rigs", json={"name": "huge", "config": {"camera": camera}})
    assert _refused_size.status_code == 422 and _refused_size.json()["field"] == field


def test_simulated_rig_with_a_shaped_panel_over_rest(app_client) -> None:
    """A lab can give a REST-created simulated rig a bowed panel behind glass; bad values are
    a 422 naming the field."""
    panel = {"bow_x_mm": 0.5, "bow_y_mm": 0.3, "glass_mm": 1.5}
    r = app_client.post("/rigs", json={"name": "bowed", "config": {"panel": panel}})
    assert r.status_code == 201, r.text
    assert r.json()["config"]["panel"] == {**panel, "twist_mm": 0.0, "glass_index": 1.52}
    bad = app_client.post("/rigs", json={"name": "bad", "config": {"panel": {"glass_mm": -1}}})
    assert bad.status_code == 422 and "panel.glass_mm" in bad.text
