"""Whole pose sequences through real stacks, run by the controller, decoded and compared.

Aravis: the controller shows patterns on a file-backed framebuffer (the real mmap path);
the GigE Vision fake camera (real Aravis stack on loopback) renders what that framebuffer
holds through the hw_mocks optics and sensor; latency is measured by the setup helper.
OpenCV: the simulated frames recorded as 16-bit PNGs replay through cv2.VideoCapture.
Both are decoded and compared with the simulated path and with ground truth.
"""

from __future__ import annotations

import re
import tempfile
from pathlib import Path

import numpy as np
import pytest

from acquisition.clock import RealClock
from acquisition.controller import ControllerOptions, capture_pose
from acquisition.display.framebuffer import FramebufferDisplay, FramebufferGeometry
from acquisition.patterns import build_plan, render_frame
from acquisition.protocols import CameraSettings
from acquisition.rig import Rig
from acquisition.setup import measure_latency
from acquisition.sinks import MemoryFrameStore
from calibration.decode import decode_stack
from hw_mocks.cameras import mild_pinhole
from hw_mocks.optics import OpticalSetup
from hw_mocks.poses import look_at_pose
from hw_mocks.sensor import SensorModel
from hw_mocks.synthetic import render_plan_frames
from tests.hw_aravis_support import fake_camera_lock, require_aravis

CAM_W, CAM_H = 80, 60
SCREEN_W, SCREEN_H, PITCH = 160, 120, 0.5
EXPOSURE_S = 0.02
FAKE_TRIGGER_LATENCY_S = 0.045


@pytest.fixture(scope="module")
def world():
    """Plan, optical setup (camera sees the screen) and a 16-bit sensor."""
    plan = build_plan(SCREEN_W, SCREEN_H, PITCH, preset="fast")
    camera = mild_pinhole(CAM_W, CAM_H)
    pose = look_at_pose(plan.screen, distance_mm=80.0, tilt_deg=10.0)
    setup = OpticalSetup(camera, pose, plan.screen, blur_sigma_screen_px=0.7, vignetting=0.2,
                         irradiance_scale=1.5e6)
    sensor = SensorModel(bit_depth=16, full_well_e=60000.0, read_noise_e=4.0)
    return plan, setup, sensor


def run_pose(plan, display, camera, settings: CameraSettings, options: ControllerOptions):
    """The controller captures one pose on these devices; returns the frame stack."""
    rig = Rig(display, camera, RealClock(), settings, plan.screen)
    store = MemoryFrameStore()
    result = capture_pose(rig, plan, store, options=options)
    assert result.status == "complete", result.reason
    return store.stack(len(plan.frames)), result


def simulated_maps(world, seed: int):
    plan, setup, sensor = world
    frames, _ = render_plan_frames(plan, setup, sensor, exposure_s=EXPOSURE_S, dither=None,
                                   rng=np.random.default_rng(seed))
    return frames, decode_stack(plan, frames, noise=sensor)


def assert_maps_agree(a, b, truth, *, min_valid: float = 0.5) -> None:
    """Both decodings valid on most visible pixels, equal within their combined noise."""
    both = a.mask & b.mask
    visible = truth["visible"]
    assert both.sum() >= min_valid * visible.sum()
    for axis in ("x", "y"):
        da = getattr(a, axis)[both] - getattr(b, axis)[both]
        sig = np.hypot(getattr(a, f"sigma_{axis}")[both], getattr(b, f"sigma_{axis}")[both])
        z = np.abs(da) / sig
        assert np.mean(z < 4.0) > 0.99, f"{axis}: median |z| {np.median(z):.2f}"
        seen = both & visible & np.isfinite(truth[f"{axis}_true"])
        err = np.abs(getattr(a, axis)[seen] - truth[f"{axis}_true"][seen])
        sig_a = getattr(a, f"sigma_{axis}")[seen]
        assert np.median(err) < 0.1, f"{axis}: median error {np.median(err):.3f} px"
        assert np.mean(err < 4 * sig_a + 0.02) > 0.98, "errors exceed the predicted sigma"


def test_opencv_replay_of_recorded_frames_decodes_like_the_simulation(world, tmp_path):
    from acquisition.camera.opencv_capture import OpenCvCamera
    from tests.acquisition.test_hw_opencv import write_sequence

    plan, setup, sensor = world
    frames, maps_sim = simulated_maps(world, seed=1)
    cam = OpenCvCamera(write_sequence(tmp_path / "pose0", frames))
    geo = FramebufferGeometry.standard(SCREEN_W, SCREEN_H, 32, refresh_hz=500.0)
    fb = Path(tempfile.mktemp(prefix="phasecal-fb-", dir="/dev/shm"))
    fb.write_bytes(bytes(geo.size_bytes))
    display = FramebufferDisplay(fb, geometry=geo)
    try:
        settings = CameraSettings(pixel_format="Mono16", trigger_mode="software")
        # A recording has no display latency to measure and cannot re-capture references.
        replayed, _ = run_pose(plan, display, cam, settings,
                               ControllerOptions(latency_s=0.0, integrity=False, dither=None))
    finally:
        cam.close()
        display.close()
        fb.unlink()
    np.testing.assert_array_equal(replayed, frames)  # bit-exact through cv2.VideoCapture
    maps = decode_stack(plan, replayed, noise=sensor)
    np.testing.assert_array_equal(maps.mask, maps_sim.mask)
    _, maps_other = simulated_maps(world, seed=2)  # another noise draw of the simulation
    assert_maps_agree(maps, maps_other, setup.truth())


def test_aravis_fake_camera_sequence_decodes_like_the_simulation(world):
    require_aravis()
    from acquisition.camera.aravis_camera import AravisCamera
    from acquisition.camera.aravis_fake import FakeGigECamera

    plan, setup, sensor = world
    geo = FramebufferGeometry.standard(SCREEN_W, SCREEN_H, 32, refresh_hz=120.0)
    fb = Path(tempfile.mktemp(prefix="phasecal-fb-", dir="/dev/shm"))
    fb.write_bytes(bytes(geo.size_bytes))
    screen_memory = np.memmap(fb, np.uint8, "r", shape=(SCREEN_H, SCREEN_W, 4))
    rng = np.random.default_rng(3)

    def light_from_screen(req):
        """The monitor lights the scene with what its framebuffer holds right now."""
        linear = screen_memory[:, :, 0].astype(np.float32) / 255.0  # blue byte = grey code
        irradiance = setup.render_irradiance(linear)
        return sensor.expose(irradiance, req.exposure_us * 1e-6, float(req.gain), rng)

    with fake_camera_lock():
        fake = FakeGigECamera("PHASECAL-E2E", light_from_screen)
        display = FramebufferDisplay(fb, geometry=geo, clock=RealClock())
        cam = AravisCamera("127.0.0.1", clock=RealClock(), region=(0, 0, CAM_W, CAM_H))
        try:
            settings = CameraSettings(exposure_s=EXPOSURE_S, pixel_format="Mono16",
                                      trigger_mode="software")
            # Latency measured by the setup helper; integrity references re-captured. The
            # fake polls for software triggers once per frame period (40 ms at its 25 Hz),
            # so an exposure can start that long after the trigger. Its frames then start
            # 16 ms or more after a flip (2 refreshes at 120 Hz), often too late to tell
            # a latency of 0 from 1 or 2 periods: the measurement then says so rather than
            # guess (the truth, 0, among the candidates: the fake reads the framebuffer
            # memory at once), and the pose runs with the truth.
            lat = measure_latency(display, cam, RealClock(), settings)
            assert 0 in (lat.periods, *lat.undecided), lat
            latency = 0.0 if lat.undecided else lat.latency_s
            options = ControllerOptions(dither=None, grab_timeout_s=2.0, latency_s=latency,
                                        trigger_overhead_s=FAKE_TRIGGER_LATENCY_S)
            stack, result = run_pose(plan, display, cam, settings, options)
        finally:
            cam.close()
            display.close()
            fake.stop()
            fb.unlink()
    assert fake.last_error is None
    # The fake sees the framebuffer memory at once: zero latency (one period if the host
    # stalls between the fake's timestamp and its read of the memory).
    assert result.latency_s <= 1 / 120.0 + 1e-9
    maps = decode_stack(plan, stack, noise=sensor)
    _, maps_sim = simulated_maps(world, seed=4)
    assert_maps_agree(maps, maps_sim, setup.truth())


def test_render_frame_reaches_the_framebuffer_bytes(world):
    plan = world[0]
    geo = FramebufferGeometry.standard(SCREEN_W, SCREEN_H, 32, refresh_hz=500.0)
    fb = Path(tempfile.mktemp(prefix="phasecal-fb-", dir="/dev/shm"))
    fb.write_bytes(bytes(geo.size_bytes))
    d = FramebufferDisplay(fb, geometry=geo)
    img = render_frame(plan, 5)
    d.show(img)
    d.close()
    mem = np.fromfile(fb, np.uint8).reshape(SCREEN_H, SCREEN_W, 4)
    fb.unlink()
    np.testing.assert_array_equal(mem[:, :, 1], img)
    assert MemoryFrameStore  # the sink type the sequences fill


def test_check_command_on_the_aravis_rig(world, capsys):
    """`phasecal check`'s checks (the controller's setup helpers) through the real stack."""
    require_aravis()
    from acquisition.camera.aravis_camera import AravisCamera
    from acquisition.camera.aravis_fake import FakeGigECamera
    from api.commands.check import _print, check_rig

    _plan, setup, sensor = world
    geo = FramebufferGeometry.standard(SCREEN_W, SCREEN_H, 32, refresh_hz=120.0)
    fb = Path(tempfile.mktemp(prefix="phasecal-fb-", dir="/dev/shm"))
    fb.write_bytes(bytes(geo.size_bytes))
    screen_memory = np.memmap(fb, np.uint8, "r", shape=(SCREEN_H, SCREEN_W, 4))
    gamma = 2.2  # the "monitor" of this rig is non-linear: check must find it
    rng = np.random.default_rng(6)

    def light_from_screen(req):
        linear = (screen_memory[:, :, 0].astype(np.float32) / 255.0) ** gamma
        irradiance = setup.render_irradiance(linear)
        return sensor.expose(irradiance, req.exposure_us * 1e-6, float(req.gain), rng)

    with fake_camera_lock():
        fake = FakeGigECamera("PHASECAL-CHECK", light_from_screen)
        display = FramebufferDisplay(fb, geometry=geo, clock=RealClock())
        cam = AravisCamera("127.0.0.1", clock=RealClock(), region=(0, 0, CAM_W, CAM_H))
        try:
            settings = CameraSettings(exposure_s=0.005, pixel_format="Mono16",
                                      trigger_mode="software")
            found = check_rig(Rig(display, cam, RealClock(), settings, _plan.screen), target=0.7)
        finally:
            cam.close()
            display.close()
            fake.stop()
            fb.unlink()
    assert found["latency"]["periods"] <= 1
    assert abs(found["exposure"]["fraction_of_max"] - 0.7) <= 0.05 * 0.7
    flats = found["flats"]
    visible = setup.truth()["visible"].mean()
    assert abs(flats["screen_fraction"] - visible) < 0.05
    assert flats["saturated_fraction"] == 0.0
    assert "error" not in found["display_response"], found["display_response"]
    assert found["display_response"]["gamma"] == pytest.approx(gamma, abs=0.15)
    _print(found)
    out = capsys.readouterr().out
    assert re.search(r"latency: [01] refresh periods", out) and "gamma ~2." in out
