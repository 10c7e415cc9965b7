"""Rig configs (TOML/JSON), opening hardware rigs on real backends, device listing, CLI."""

from __future__ import annotations

import json
import tempfile
from pathlib import Path

import numpy as np
import pytest

from acquisition.rig import (
    RigConfig,
    RigConfigError,
    load_rig_config,
    open_rig,
    parse_rig_config,
)
from api.cli import main
from hw_mocks.rig import open_simulated_rig
from tests.acquisition.test_hw_opencv import write_sequence

DOCS = Path(__file__).resolve().parents[2] / "docs" / "rigs"


@pytest.fixture
def fb_path():
    path = Path(tempfile.mktemp(prefix="phasecal-fb-", dir="/dev/shm"))
    path.write_bytes(bytes(32 * 24 * 4))
    yield path
    path.unlink(missing_ok=True)


def _hardware_toml(fb: Path, frames: str, extra: str = "") -> str:
    return f"""
kind = "hardware"
name = "bench"
[screen]
pitch_mm = [0.25, 0.26]
[display]
backend = "framebuffer"
device = "{fb}"
width = 32
height = 24
refresh_hz = 240.0
[camera]
backend = "opencv"
source = "{frames}"
[settings]
exposure_s = 0.005
pixel_format = "Mono16"
trigger_mode = "software"
{extra}
"""


def test_example_configs_parse() -> None:
    files = sorted(DOCS.glob("*.toml"))
    assert len(files) >= 4
    for f in files:
        cfg = load_rig_config(f)
        assert cfg.format == "phasecal.rig/1"
    sdl = load_rig_config(DOCS / "sdl-aravis.toml")
    assert sdl.camera.backend == "aravis" and sdl.trigger_box.vendor_id == 0x16C0
    assert sdl.settings.to_settings().trigger_mode == "hardware"


def test_open_hardware_rig_from_toml(tmp_path: Path, fb_path: Path) -> None:
    frames = np.random.default_rng(0).integers(0, 65535, (3, 6, 8)).astype(np.uint16)
    seq = write_sequence(tmp_path / "rec", frames)
    cfg_file = tmp_path / "rig.toml"
    cfg_file.write_text(_hardware_toml(fb_path, seq))
    rig = open_rig(load_rig_config(cfg_file), simulator=open_simulated_rig)
    try:
        assert (rig.screen.width_px, rig.screen.height_px) == (32, 24)
        assert rig.screen.pitch_mm == (0.25, 0.26)
        assert rig.display.info.refresh_hz == 240.0
        assert rig.camera.info.bit_depth == 16
        assert rig.settings.exposure_s == 0.005 and rig.simulated is None
        rig.display.show(np.full((24, 32), 77, np.uint8))
        assert np.fromfile(fb_path, np.uint8)[:4].tolist() == [77, 77, 77, 0]
        rig.camera.start()
        rig.camera.trigger()
        np.testing.assert_array_equal(rig.camera.grab(1.0).image, frames[0])
    finally:
        rig.close()
        rig.close()  # idempotent


def test_json_config_is_equivalent(tmp_path: Path, fb_path: Path) -> None:
    import tomllib

    data = tomllib.loads(_hardware_toml(fb_path, "x/frame_%04d.png"))
    path = tmp_path / "rig.json"
    path.write_text(json.dumps(data))
    assert load_rig_config(path) == RigConfig.model_validate(data)


@pytest.mark.parametrize(
    "edit, message",
    [
        (lambda s: s.replace("pitch_mm = [0.25, 0.26]", ""), "screen.pitch_mm is missing"),
        (lambda s: s.replace('backend = "framebuffer"', 'backend = "crt"'), "display"),
        (lambda s: s.replace("refresh_hz = 240.0", "refresh_hz = -1"), "display.framebuffer"),
        (lambda s: s + "\n[camera.extra]\nx = 1\n", "camera.opencv.extra"),
        (lambda s: s.replace('kind = "hardware"', 'kind = "simulated"'), "kind 'simulated'"),
        (lambda s: s.replace("[screen]", "[screen]\nwidth_px = 0"), "screen.width_px"),
    ],
)
def test_invalid_configs_name_the_field(tmp_path: Path, fb_path: Path, edit, message) -> None:
    path = tmp_path / "bad.toml"
    path.write_text(edit(_hardware_toml(fb_path, "x/frame_%04d.png")))
    with pytest.raises(RigConfigError, match=message) as info:
        load_rig_config(path)
    assert str(path) in str(info.value)


def test_malformed_toml_and_missing_file(tmp_path: Path) -> None:
    bad = tmp_path / "rig.toml"
    bad.write_text("kind = \n")
    with pytest.raises(RigConfigError, match="not valid TOML"):
        load_rig_config(bad)
    with pytest.raises(FileNotFoundError, match="no such file"):
        load_rig_config(tmp_path / "none.toml")


def test_failed_open_closes_what_was_opened(tmp_path: Path, fb_path: Path) -> None:
    from acquisition.errors import CameraDisconnected

    cfg = tmp_path / "rig.toml"
    cfg.write_text(_hardware_toml(fb_path, str(tmp_path / "missing.mkv")))
    with pytest.raises(CameraDisconnected, match="does not exist"):
        open_rig(load_rig_config(cfg), simulator=open_simulated_rig)


def test_screen_size_must_match_the_display(tmp_path: Path, fb_path: Path) -> None:
    frames = np.zeros((1, 4, 4), np.uint8)
    seq = write_sequence(tmp_path / "rec", frames)
    cfg = tmp_path / "rig.toml"
    cfg.write_text(_hardware_toml(fb_path, seq).replace("[screen]", "[screen]\nwidth_px = 30"))
    with pytest.raises(RigConfigError, match="30x24 px in the config, the display is 32x24"):
        open_rig(load_rig_config(cfg), simulator=open_simulated_rig)


def test_list_devices_on_a_fake_system(tmp_path: Path, monkeypatch) -> None:
    from acquisition.discovery import list_device_nodes, list_devices
    from tests.acquisition.test_hw_usb import FakeBackend, _device

    monkeypatch.setenv("SDL_VIDEODRIVER", "dummy")
    dev, sysfs = tmp_path / "dev", tmp_path / "sys"
    (sysfs / "graphics" / "fb1").mkdir(parents=True)
    (sysfs / "video4linux" / "video2").mkdir(parents=True)
    (sysfs / "graphics" / "fb1" / "virtual_size").write_text("800,480\n")
    (sysfs / "graphics" / "fb1" / "bits_per_pixel").write_text("16\n")
    (sysfs / "video4linux" / "video2" / "name").write_text("HD Webcam\n")
    dev.mkdir()
    (dev / "fb1").touch()
    (dev / "video2").touch()
    usb = FakeBackend([_device(0x2676, 0xBA02, ("Basler", "a2A", "77"), [(0xEF, 5)])])
    found = list_devices(usb_backend=usb, dev_root=dev, sysfs_root=sysfs)
    by_backend = {d.backend: d for d in found}
    assert by_backend["simulated"].config == {"kind": "simulated"}
    assert by_backend["framebuffer"].id == str(dev / "fb1")
    assert "800x480 16 bpp" in by_backend["framebuffer"].description
    assert by_backend["opencv"].description == "HD Webcam"
    assert "virtual" in by_backend["sdl"].description  # dummy driver: no real screen
    assert "usb3vision 2676:ba02 Basler a2A serial 77" in by_backend["aravis"].description
    assert not any(d.id == "127.0.0.1" for d in found)  # Aravis only when asked
    # what a REST client may name: the /dev nodes, listed exactly as GET /devices lists them
    assert list_device_nodes(dev, sysfs) == [by_backend["framebuffer"], by_backend["opencv"]]


def test_devices_command_json(capsys, monkeypatch) -> None:
    monkeypatch.setenv("SDL_VIDEODRIVER", "dummy")
    assert main(["devices", "--json"]) == 0
    data = json.loads(capsys.readouterr().out)
    assert data[0]["backend"] == "simulated" and data[0]["config"] == {"kind": "simulated"}
    assert main(["devices"]) == 0
    assert "simulated" in capsys.readouterr().out


def test_simulated_rig_is_the_default() -> None:
    with pytest.raises(RigConfigError, match="no simulator available"):
        open_rig(RigConfig())  # acquisition never reaches into hw_mocks by itself
    rig = open_rig(RigConfig(), simulator=open_simulated_rig)
    try:
        assert rig.simulated is not None and rig.camera is rig.simulated.camera
        assert rig.screen == rig.simulated.screen
        assert rig.display.info.width_px == rig.screen.width_px
    finally:
        rig.close()
    cfg = parse_rig_config({"kind": "simulated", "clock": "real",
                            "camera": {"model": "wide_fisheye", "width": 64, "height": 48},
                            "settings": {"exposure_s": 0.01, "pixel_format": "Mono12",
                                         "trigger_mode": "software"}})
    rig = open_rig(cfg, simulator=open_simulated_rig)
    try:
        assert (rig.camera.info.width, rig.camera.info.height) == (64, 48)
        assert rig.settings.exposure_s == 0.01
        assert type(rig.clock).__name__ == "RealClock"
    finally:
        rig.close()
    with pytest.raises(RigConfigError, match="clock 'virtual' is only for simulated"):
        parse_rig_config({"kind": "hardware", "clock": "virtual", "screen": {"pitch_mm": 0.3},
                          "display": {"backend": "sdl"},
                          "camera": {"backend": "aravis", "device": "x"}})


def test_check_command_errors_are_one_line(tmp_path: Path, capsys) -> None:
    assert main(["check", "--rig", str(tmp_path / "none.toml")]) == 1
    assert "no such rig config file" in capsys.readouterr().err
    assert main(["check", "--target", "1.5"]) == 1
    assert "--target" in capsys.readouterr().err
    bad = tmp_path / "bad.toml"
    bad.write_text('kind = "hardware"\n')
    assert main(["check", "--rig", str(bad)]) == 1
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "kind 'hardware' needs real backends" in err


def test_simulated_rig_with_a_shaped_panel_behind_glass(tmp_path: Path) -> None:
    """`[panel]` gives a simulated rig a bowed panel behind cover glass: the camera sees the
    screen points hw_mocks' exact tracer gives; bad values and hardware rigs are refused."""
    from hw_mocks.panel import PanelShape

    cfg_file = tmp_path / "bowed.toml"
    cfg_file.write_text('kind = "simulated"\n[camera]\nwidth = 64\nheight = 48\n'
                        "[panel]\nbow_x_mm = 0.5\nbow_y_mm = 0.3\nglass_mm = 1.5\n")
    cfg = load_rig_config(cfg_file)
    assert cfg.panel is not None and cfg.panel.glass_index == 1.52
    shaped, ideal = (open_rig(c, simulator=open_simulated_rig)
                     for c in (cfg, parse_rig_config({"camera": {"width": 64, "height": 48}})))
    try:
        assert shaped.simulated.optics.panel == PanelShape(0.5, 0.3, 0.0, 1.5, 1.52)
        t_shaped, t_ideal = shaped.simulated.truth(), ideal.simulated.truth()
        assert t_shaped["panel"] == PanelShape(0.5, 0.3, 0.0, 1.5, 1.52)
        seen = t_shaped["visible"] & t_ideal["visible"]
        moved_mm = np.abs(t_shaped["x_true"] - t_ideal["x_true"])[seen] * 0.25
        assert seen.sum() > 1000 and 0.01 < float(np.median(moved_mm)) < 2.0
    finally:
        shaped.close()
        ideal.close()
    for panel, message in (({"glass_mm": -1.0}, "panel.glass_mm"),
                           ({"glass_index": 0.5}, "panel.glass_index"),
                           ({"bow_x_mm": 3.0, "glass_mm": 0.5}, "through the 0.5 mm glass"),
                           ({"bow": 0.5}, "panel.bow: Extra inputs")):
        with pytest.raises(RigConfigError, match=message):
            parse_rig_config({"kind": "simulated", "panel": panel})
    with pytest.raises(RigConfigError, match="panel describes a simulated screen"):
        parse_rig_config({"kind": "hardware", "screen": {"pitch_mm": 0.3},
                          "display": {"backend": "sdl"},
                          "camera": {"backend": "aravis", "device": "x"},
                          "panel": {"glass_mm": 1.0}})


def _two_camera_toml(fb: Path, first: str, second: str) -> str:
    """The hardware rig above with its camera replaced by two named ones."""
    one = _hardware_toml(fb, first)
    head = one[:one.index("[camera]")]
    return head + f"""
[[cameras]]
name = "left"
backend = "opencv"
source = "{first}"
[[cameras]]
name = "right"
backend = "opencv"
source = "{second}"
[cameras.settings]
exposure_s = 0.008
pixel_format = "Mono16"
trigger_mode = "software"
[settings]
exposure_s = 0.005
pixel_format = "Mono16"
trigger_mode = "software"
"""


def test_open_a_two_camera_rig_of_different_sizes(tmp_path: Path, fb_path: Path) -> None:
    rng = np.random.default_rng(1)
    small = rng.integers(0, 65535, (2, 6, 8)).astype(np.uint16)
    large = rng.integers(0, 65535, (2, 10, 12)).astype(np.uint16)
    cfg_file = tmp_path / "rig.toml"
    cfg_file.write_text(_two_camera_toml(fb_path, write_sequence(tmp_path / "a", small),
                                         write_sequence(tmp_path / "b", large)))
    cfg = load_rig_config(cfg_file)
    assert [name for name, _, _ in cfg.camera_entries()] == ["left", "right"]
    rig = open_rig(cfg, simulator=open_simulated_rig)
    try:
        assert list(rig.cameras) == ["left", "right"] and rig.reference == "left"
        assert rig.camera is rig.cameras["left"]
        assert rig.settings_for("left").exposure_s == 0.005
        assert rig.settings_for("right").exposure_s == 0.008
        sizes = {n: (c.info.width, c.info.height) for n, c in rig.cameras.items()}
        assert sizes == {"left": (8, 6), "right": (12, 10)}
    finally:
        rig.close()


def test_mixed_backends_parse_and_a_one_camera_rig_keeps_its_form() -> None:
    cfg = parse_rig_config({"kind": "hardware", "screen": {"pitch_mm": 0.2},
                            "display": {"backend": "sdl"},
                            "cameras": [{"name": "a", "backend": "opencv", "source": 1},
                                        {"name": "b", "backend": "aravis", "device": "x"}]})
    assert [c.backend for _, c, _ in cfg.camera_entries()] == ["opencv", "aravis"]
    assert parse_rig_config(cfg.model_dump(mode="json")) == cfg  # stored and read back
    one = parse_rig_config({"camera": {"width": 64}})
    assert one.cameras is None and one.camera_entries()[0][0] == "cam0"


@pytest.mark.parametrize("cameras, message", [
    ([{"name": "a"}, {"name": "a"}], r"duplicate camera name\(s\) \['a'\]"),
    ([{"name": "a", "backend": "webcam"}], "cameras.0: Input tag 'webcam'"),
    ([], "cameras: List should have at least 1 item"),
    ([{"name": "a b"}], "cameras.0.simulated.name: String should match"),
    ([{"width": 64}], "cameras.0.simulated.name: Field required"),
])
def test_invalid_camera_lists_name_the_field(cameras, message) -> None:
    with pytest.raises(RigConfigError, match=message):
        parse_rig_config({"cameras": cameras})
    with pytest.raises(RigConfigError, match=r"give camera .* or cameras .*, not both"):
        parse_rig_config({"camera": {}, "cameras": [{"name": "a"}]})
    with pytest.raises(RigConfigError, match="kind 'hardware' needs real backends; "
                       "\\[\"camera 'b'\"\\] simulated"):
        parse_rig_config({"kind": "hardware", "screen": {"pitch_mm": 0.2},
                          "display": {"backend": "sdl"},
                          "cameras": [{"name": "a", "backend": "opencv"},
                                      {"name": "b", "backend": "simulated"}]})


def test_simulated_rig_with_cameras_placed_around_the_reference() -> None:
    rig = open_simulated_rig(parse_rig_config({"cameras": [
        {"name": "ref"}, {"name": "wide", "model": "wide_fisheye", "width": 96, "height": 80,
                          "trigger_latency_s": 5e-4, "timestamp_jitter_s": 1e-4},
        {"name": "fixed", "extrinsics": {"rvec": [0, 0.1, 0], "t_mm": [-20, 0, 0]}}]}))
    sim = rig.simulated
    assert list(rig.cameras) == ["ref", "wide", "fixed"]
    assert (rig.cameras["wide"].info.width, rig.cameras["wide"].info.height) == (96, 80)
    np.testing.assert_allclose(sim.mounts["ref"].rotation, np.eye(3))
    np.testing.assert_allclose(sim.mounts["fixed"].translation_mm, [-20, 0, 0])
    wide = sim.mounts["wide"]
    assert np.linalg.norm(wide.translation_mm) > 1  # placed beside the reference, by default
    np.testing.assert_allclose(wide.rotation @ wide.rotation.T, np.eye(3), atol=1e-12)
    seen = {n: np.isfinite(sim.truth(n)["x_true"]).mean() for n in rig.cameras}
    assert min(seen.values()) > 0.05, seen  # every camera sees the screen from where it is
