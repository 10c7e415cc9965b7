"""Simulated display, camera and rig: timing, mixing, queues, faults, settings errors."""

from __future__ import annotations

import numpy as np
import pytest

from acquisition.conformance import check_camera, check_display
from acquisition.errors import CameraDisconnected, CameraTimeout, DeviceSettingsError
from acquisition.protocols import CameraSettings
from calibration.shared.plan import ScreenGeometry
from hw_mocks.camera import CameraFaults
from hw_mocks.cameras import mild_pinhole
from hw_mocks.clock import VirtualClock
from hw_mocks.display import SimulatedDisplay
from hw_mocks.rig import SimulatedRig

SCREEN = ScreenGeometry(160, 100, (1.0, 1.0))


def rig(**kw) -> SimulatedRig:
    return SimulatedRig(mild_pinhole(80, 60), SCREEN, **kw)


def test_display_passes_protocol():
    clock = VirtualClock()
    check_display(SimulatedDisplay(64, 48, clock), clock)


def test_conformance_kit_catches_a_broken_display():
    """The shipped kit fails a display that reports flips before show() was called."""

    class EarlyFlips(SimulatedDisplay):
        def show(self, image):
            return super().show(image) - 1.0

    clock = VirtualClock()
    with pytest.raises(AssertionError, match="must not precede"):
        check_display(EarlyFlips(64, 48, clock), clock)


@pytest.mark.parametrize("mode", ["software", "free-running"])
def test_camera_passes_protocol(mode):
    r = rig()
    check_camera(r.camera, r.clock, r.with_settings(trigger_mode=mode, exposure_s=0.01))


def test_scanout_latency_and_row_mix():
    clock = VirtualClock()
    d = SimulatedDisplay(8, 10, clock, refresh_hz=50.0, latency_periods=2)
    p = 0.02
    f1 = d.show(np.full((10, 8), 255, np.uint8))
    assert f1 == pytest.approx(p)
    shown, w = d.row_weights(f1 + 2 * p, f1 + 2 * p + p)  # during scan-out of image 1
    assert [s.image_id for s in shown] == [0, 1]
    # row r switches at flip + 2P + (r/H) P: its weight of image 1 is 1 - r/H.
    np.testing.assert_allclose(w[1], 1 - np.arange(10) / 10)
    np.testing.assert_allclose(d.emitted(f1 + 3 * p, f1 + 4 * p), 1.0)
    np.testing.assert_allclose(d.emitted(0.0, f1 + 2 * p), 0.0)


def test_gamma_response():
    clock = VirtualClock()
    d = SimulatedDisplay(4, 4, clock, gamma=2.2, latency_periods=0)
    f = d.show(np.full((4, 4), 128, np.uint8))
    lin = d.emitted(f + 1 / 60, f + 2 / 60)
    np.testing.assert_allclose(lin, (128 / 255) ** 2.2, rtol=1e-5)


def test_free_running_queue_drops_oldest_and_flush():
    r = rig(camera={"buffer_depth": 4, "default_frame_rate_hz": 30.0})
    cam = r.camera
    cam.configure(r.with_settings(trigger_mode="free-running", exposure_s=0.01))
    cam.start()
    r.clock.sleep_until(1.0)  # ~30 frames produced, only the newest 4 kept
    seqs = [cam.grab(0.1).sequence for _ in range(4)]
    assert seqs == sorted(seqs) and seqs[-1] - seqs[0] == 3 and seqs[0] > 20
    t = r.clock.now()
    cam.flush()
    assert cam.grab(0.1).timestamp_s >= t - 1e-3


def test_frame_straddling_a_change_is_mixed_in_truth():
    r = rig(display={"latency_periods": 1})
    cam, d = r.camera, r.display
    cam.configure(r.with_settings(exposure_s=0.01))
    cam.start()
    flip = d.show(np.zeros((100, 160), np.uint8))
    flip2 = d.show(np.full((100, 160), 255, np.uint8))
    r.clock.sleep_until(flip2 + 1 / 60 + 0.5 / 60 - 0.005)  # mid scan-out of the white image
    cam.trigger()
    fr = cam.grab(1.0)
    truth = cam.truth[fr.sequence]
    assert not truth.pure and len(truth.image_ids) == 2 and flip < flip2


def test_unplug_and_failed_reconnects():
    r = rig(faults=CameraFaults(unplug_after_frames=2, reconnect_failures=2))
    cam = r.camera
    cam.configure(r.camera_settings)
    cam.start()
    for _ in range(2):
        cam.trigger()
        cam.grab(1.0)
    with pytest.raises(CameraDisconnected):
        cam.trigger()
    for _ in range(2):
        with pytest.raises(CameraDisconnected, match="reconnect failed"):
            cam.reconnect()
    cam.reconnect()
    cam.start()
    cam.trigger()
    assert cam.grab(1.0).image.shape == (60, 80)


def test_injected_timeout():
    r = rig(faults=CameraFaults(timeout_grabs=frozenset({1})))
    cam = r.camera
    cam.configure(r.camera_settings)
    cam.start()
    cam.trigger()
    with pytest.raises(CameraTimeout):
        cam.grab(0.5)


@pytest.mark.parametrize("change, match", [
    ({"exposure_s": -0.01}, "exposure_s"),
    ({"pixel_format": "RGB8"}, "pixel_format"),
    ({"pixel_format": "Mono16"}, "pixel_format"),  # 12-bit sensor: no 16-bit format
    ({"trigger_mode": "hardware"}, "trigger_mode"),
    ({"trigger_mode": "free-running", "frame_rate_hz": 60.0, "exposure_s": 0.05}, "too high"),
    ({"gain_db": -3.0}, "gain_db"),
])
def test_bad_settings(change, match):
    r = rig()
    base = CameraSettings(exposure_s=0.01, pixel_format="Mono12", trigger_mode="software")
    with pytest.raises(DeviceSettingsError, match=match):
        r.camera.configure(CameraSettings(**{**base.__dict__, **change}))


def test_bit_depths():
    r = rig(sensor={"bit_depth": 16})
    for fmt, dtype, top in (("Mono8", np.uint8, 255), ("Mono16", np.uint16, 65535)):
        r.camera.configure(r.with_settings(pixel_format=fmt, exposure_s=0.2))
        r.camera.start()
        r.display.show(np.full((100, 160), 255, np.uint8))
        r.clock.sleep_until(r.clock.now() + 0.1)
        r.camera.trigger()
        img = r.camera.grab(1.0).image
        assert img.dtype == dtype and img.max() == top  # saturated at the format's top


def test_rig_from_config_and_unknown_key():
    sim = SimulatedRig.from_config({"kind": "simulated", "camera": {"model": "mild_pinhole",
                                                                    "width": 40, "height": 30}})
    assert sim.camera.info.width == 40
    with pytest.raises(DeviceSettingsError, match="latency_frames"):
        SimulatedRig.from_config({"display": {"latency_frames": 2}})


def test_row_weights_over_a_long_history_match_the_full_computation():
    """row_weights looks only at the images near the window (a 10 s history is hundreds of
    images): the same images and weights as weighing every remembered image."""
    from hw_mocks.display import SimulatedDisplay

    clock = VirtualClock()
    display = SimulatedDisplay(32, 20, clock, latency_periods=2, history_s=1e9)
    rng = np.random.default_rng(5)
    for k in range(400):
        display.show(np.full((20, 32), k % 256, np.uint8))
        clock.advance(float(rng.uniform(0, 3 / 60)))

    def full(t0: float, t1: float) -> tuple[list[int], np.ndarray]:
        hist = display.history()
        frac = np.arange(20) / 20
        starts = np.stack([np.broadcast_to(h.flip_s + (2 + frac) / 60, frac.shape)
                           for h in hist])
        ends = np.vstack([starts[1:], np.full((1, 20), np.inf)])
        w = np.clip(np.minimum(ends, t1) - np.maximum(starts, t0), 0.0, None) / (t1 - t0)
        keep = w.max(axis=1) > 0
        return [h.image_id for h, k in zip(hist, keep, strict=True) if k], w[keep]

    first, now = display.history()[1].flip_s, clock.now()
    for _ in range(500):
        t0 = float(rng.uniform(first, now + 0.1))
        t1 = t0 + float(rng.uniform(1e-4, 0.1))
        shown, weights = display.row_weights(t0, t1)
        ids, want = full(t0, t1)
        assert [h.image_id for h in shown] == ids
        np.testing.assert_allclose(weights, want, rtol=0, atol=1e-12)


def _replay_rig():
    """A small simulated rig whose camera replays frames, its plan, and `capture(store)`:
    one pose through the controller into `store`, returning the controller's result."""
    from acquisition.controller import ControllerOptions, capture_pose
    from acquisition.patterns import build_plan
    from hw_mocks.rig import SimulatedRig

    screen = ScreenGeometry(320, 200, (0.5, 0.5))
    plan = build_plan(320, 200, 0.5)
    r = SimulatedRig(mild_pinhole(80, 60), screen, display={"history_s": 1e9},
                     camera={"replay": True, "timestamp_jitter_s": 0.0})
    settings = r.with_settings(exposure_s=0.004, trigger_mode="software")
    opts = ControllerOptions(latency_s=2 / 60)
    return r, plan, lambda store: capture_pose(r.rig, plan, store, settings=settings,
                                               options=opts)


def test_replay_tears_a_frame_from_replayed_frames_instead_of_rendering(monkeypatch):
    """With `replay`, a pose of the same screen content renders nothing, even when a late
    trigger tears a frame: the torn frame is made of rows of the images it mixes, those
    of the image that held each row longest (a horizontal tear, both images in it)."""
    from acquisition.sinks import MemoryFrameStore

    r, plan, capture = _replay_rig()
    first = MemoryFrameStore()
    assert capture(first).status == "complete"
    renders: list[int] = []
    render = r.camera.optics.render_irradiance
    monkeypatch.setattr(r.camera.optics, "render_irradiance",
                        lambda light: renders.append(1) or render(light))
    delivered: dict[int, np.ndarray] = {}  # every frame of the second pose, by sequence
    deliver = r.camera._deliver

    def recording(exp):
        frame = deliver(exp)
        delivered[frame.sequence] = frame.image
        return frame

    monkeypatch.setattr(r.camera, "_deliver", recording)
    r.camera.faults.late_triggers[r.camera._triggers + 6] = 0.02
    second = MemoryFrameStore()
    res = capture(second)
    assert res.status == "complete" and [rc.reason[:4] for rc in res.recaptures] == ["torn"]
    torn = [t for t in r.camera.truth.values() if not t.pure]
    assert torn and renders == []
    mixed = delivered[torn[0].sequence]
    pure = [delivered[t.sequence] for t in r.camera.truth.values()
            if t.pure and t.sequence in delivered]
    rows = [np.all(mixed == frame, axis=1) for frame in pure]  # its rows equal to each one's
    assert np.logical_or.reduce(rows).all()  # every row from a replayed pure frame
    assert not any(match.all() for match in rows)  # but not all from one: a tear
    np.testing.assert_array_equal(first.stack(len(plan.frames)), second.stack(len(plan.frames)))


def test_replay_renders_again_after_a_rotation_or_stray_light_change():
    """A replayed frame is the same screen content seen the same way: a screen turned about
    its origin (same translation) or more ambient light renders a new image."""
    import cv2

    from acquisition.sinks import MemoryFrameStore

    r, plan, capture = _replay_rig()

    def stack() -> np.ndarray:
        store = MemoryFrameStore()
        assert capture(store).status == "complete"
        return store.stack(len(plan.frames))

    first = stack()
    np.testing.assert_array_equal(stack(), first)  # replayed: the same content
    pose = r.camera.optics.pose
    turn = cv2.Rodrigues(np.array([0.0, 0.05, 0.0]))[0]
    r.set_pose(turn @ pose.rotation, pose.translation)
    turned = stack()
    assert np.abs(turned.astype(int) - first).max() > 10
    r.set_ambient(r.camera.optics.ambient + 2e4)
    assert (stack().astype(int) - turned).mean() > 0.5
