"""Aravis camera against the real Aravis stack: a GigE Vision fake camera on loopback."""

from __future__ import annotations

import time
from itertools import pairwise

import numpy as np
import pytest

from acquisition.clock import RealClock
from acquisition.errors import CameraDisconnected, CameraTimeout, DeviceSettingsError, FrameLost
from acquisition.protocols import CameraSettings
from tests.hw_aravis_support import fake_camera_lock, lossy_fake_camera, require_aravis

SERIAL = "PHASECAL-T1"
W, H = 64, 48


class Scene:
    """What the fake camera shows: a frame counter stamped into a chosen image."""

    def __init__(self) -> None:
        self.image: np.ndarray = np.zeros((H, W), np.uint16)
        self.count = 0
        self.requests: list = []

    def __call__(self, req) -> np.ndarray:
        self.requests.append(req)
        self.count += 1
        img = self.image.copy()
        img[0, 0] = self.count
        return img


@pytest.fixture(scope="module")
def fake():
    require_aravis()
    from acquisition.camera.aravis_fake import FakeGigECamera

    with fake_camera_lock():
        holder = {"scene": Scene()}
        holder["fake"] = FakeGigECamera(SERIAL, holder["scene"])
        yield holder
        holder["fake"].stop()


@pytest.fixture
def cam(fake):
    from acquisition.camera.aravis_camera import AravisCamera

    fake["scene"].__init__()
    c = AravisCamera("127.0.0.1", clock=RealClock(), bayer="raw", region=(0, 0, W, H))
    yield c
    c.close()


@pytest.fixture
def lossy(fake):
    """The scene's fake replaced, for one test, by Aravis' own fake losing 10% of its
    packets (a frame of 64x48 Mono16 is 7 packets: about half the frames lose one); the
    camera streams, software-triggered, Mono16."""
    from acquisition.camera.aravis_camera import AravisCamera
    from acquisition.camera.aravis_fake import FakeGigECamera

    fake["fake"].stop()
    try:
        with lossy_fake_camera(SERIAL) as lose:
            c = AravisCamera("127.0.0.1", clock=RealClock(), bayer="raw", region=(0, 0, W, H))
            try:
                c.configure(_software("Mono16"))
                _start_streaming(c)
                lose(0.1)
                yield c
            finally:
                c.close()
    finally:
        fake["fake"] = FakeGigECamera(SERIAL, fake["scene"])


def _start_streaming(cam) -> None:
    """Start and see one frame through. The first stream of a freshly started fake on a
    loaded host has been seen to stay deaf (its first packets arrive before its buffers
    and every later frame is ignored): that shows as a timeout, and a restarted stream
    works, which is what the controller does on a timeout."""
    for _ in range(3):
        cam.start()
        cam.trigger()
        try:
            cam.grab(5.0)
            return
        except CameraTimeout:
            cam.stop()
    pytest.fail(f"no frame from the fake after 3 stream starts: {cam.stream_statistics()}")


def _software(pixel_format: str = "Mono16", **kw) -> CameraSettings:
    return CameraSettings(exposure_s=0.004, gain_db=0.0, pixel_format=pixel_format,
                          trigger_mode="software", **kw)


def _grab_retriggering(cam, timeout_s: float) -> tuple[object, int]:
    """A frame, triggering again for each lost one (as the controller does); the frame
    and how many were lost on the way."""
    lost = 0
    while True:
        try:
            return cam.grab(timeout_s), lost
        except FrameLost:
            lost += 1
            cam.trigger()


def test_info_by_address(cam) -> None:
    info = cam.info
    assert info.serial == SERIAL
    assert {"Mono8", "Mono16", "BayerRG8"} <= set(info.pixel_formats)
    assert {"software", "hardware", "free-running"} == set(info.trigger_modes)


def test_exposure_and_gain_read_back_and_reach_the_sensor(cam, fake) -> None:
    applied = cam.configure(CameraSettings(exposure_s=0.0123, gain_db=3.0, pixel_format="Mono8",
                                           trigger_mode="software"))
    assert applied.exposure_s == pytest.approx(0.0123, rel=1e-3)
    assert applied.gain_db == pytest.approx(3.0)
    assert applied.trigger_mode == "software"
    cam.start()
    cam.trigger()
    cam.grab(2.0)
    req = fake["scene"].requests[-1]
    assert req.exposure_us == 12300 and req.gain == 3 and req.pixel_format == "Mono8"
    with pytest.raises(DeviceSettingsError, match=r"exposure_s 100\.0 outside"):
        cam.configure(CameraSettings(exposure_s=100.0))
    with pytest.raises(DeviceSettingsError, match="pixel_format 'Mono12Packed' not offered"):
        cam.configure(CameraSettings(pixel_format="Mono12Packed"))


@pytest.mark.parametrize("fmt", ["Mono16", "Mono8"])
def test_triggered_frames_are_exact_and_fresh(cam, fake, fmt: str) -> None:
    rng = np.random.default_rng(2)
    scene = fake["scene"]
    scene.image = rng.integers(256, 65535, size=(H, W)).astype(np.uint16)
    cam.configure(_software(fmt))
    cam.start()
    for _ in range(3):
        cam.trigger()
        frame = cam.grab(2.0)
        want = scene.image.copy()
        want[0, 0] = scene.count
        if fmt == "Mono8":
            want = (want >> 8).astype(np.uint8)
        assert frame.image.dtype == want.dtype
        np.testing.assert_array_equal(frame.image, want)


def test_no_stale_frame_after_a_trigger(cam, fake) -> None:
    scene = fake["scene"]
    cam.configure(_software("Mono16"))
    cam.start()
    cam.trigger()
    clock = RealClock()
    clock.sleep_until(clock.now() + 0.3)  # frame 1 arrives and waits in the stream
    cam.trigger()
    frame = cam.grab(2.0)
    assert int(frame.image[0, 0]) == scene.count == 2  # frame 1 was dropped as stale
    assert cam.stale_frames == 1


def test_a_slow_host_never_makes_a_fresh_frame_look_stale(cam, fake, monkeypatch) -> None:
    """A delay between popping a buffer and dating it (decoding, a loaded host) was
    counted as time the buffer had waited in the queue: its arrival, dated that much too
    early, pulled the device-to-clock offset down, and fresh triggered frames looked
    exposed before their trigger, were dropped as stale and the grab timed out."""
    from acquisition.camera import aravis_camera

    decode = aravis_camera.decode_image

    def slow_decode(*args, **kwargs):
        time.sleep(0.08)  # the host stalls right after the pop
        return decode(*args, **kwargs)

    monkeypatch.setattr(aravis_camera, "decode_image", slow_decode)
    cam.configure(_software("Mono16"))
    cam.start()
    for k in range(1, 5):
        cam.trigger()
        assert int(cam.grab(2.0).image[0, 0]) == k == fake["scene"].count
    assert cam.stale_frames == 0


def test_grab_without_trigger_times_out(cam) -> None:
    cam.configure(_software())
    cam.start()
    with pytest.raises(CameraTimeout, match=r"no frame within 0\.300 s"):
        cam.grab(0.3)


def test_free_running_and_bayer(cam, fake) -> None:
    scene = fake["scene"]
    scene.image = np.full((H, W), 120 << 8, np.uint16)
    cam.configure(CameraSettings(exposure_s=0.002, pixel_format="BayerRG8",
                                 trigger_mode="free-running", frame_rate_hz=50.0))
    cam.start()
    frames = [cam.grab(2.0) for _ in range(3)]
    assert all(f.image.dtype == np.uint8 for f in frames)
    assert np.all(frames[-1].image[1:, 1:] == 120)
    # frames in order (`sequence`, GigE block ids wrap at 16 bits); their times are upper
    # bounds, which a late first frame (a loaded host) can leave out of order by its delay
    # (seen: frame 65410 dated 14 us after 65411)
    assert all(0 < (b.sequence - a.sequence) % 65536 < 100 for a, b in pairwise(frames))
    assert all(np.isfinite(f.timestamp_s) for f in frames)
    assert cam.flush() >= 0
    assert cam.grab(2.0).timestamp_s >= frames[-1].timestamp_s


def test_unplug_is_detected_and_reconnect_recovers(cam, fake) -> None:
    from acquisition.camera.aravis_fake import FakeGigECamera

    cam.configure(_software())
    cam.start()
    cam.trigger()
    cam.grab(2.0)
    fake["fake"].stop()  # the camera vanishes from the network
    with pytest.raises(CameraDisconnected):
        cam.trigger()
        cam.grab(1.0)
    fake["fake"] = FakeGigECamera(SERIAL, fake["scene"])  # plugged back in
    cam.reconnect()
    assert (cam.info.width, cam.info.height) == (W, H)  # the region is restored too
    cam.trigger()
    assert cam.grab(2.0).image.shape == (H, W)


def test_opening_an_absent_camera_is_a_clear_error() -> None:
    require_aravis()
    from acquisition.camera.aravis_camera import AravisCamera

    with pytest.raises(CameraDisconnected, match="cannot open"):
        AravisCamera("127.0.0.1:1")  # no GigE Vision camera answers on this address form
    with pytest.raises(DeviceSettingsError, match="discovery is never implicit"):
        AravisCamera("")


def test_back_to_back_triggers_each_give_a_frame(cam, fake) -> None:
    """On a loaded host the fake's sender can stall mid-frame past the frame retention:
    that frame is lost (`FrameLost`, at once) and triggered again, never a timeout."""
    scene = fake["scene"]
    cam.configure(_software("Mono16"))
    _start_streaming(cam)  # (a fresh fake's first stream can stay deaf on a loaded host)
    seen, lost_before = scene.count, cam.incomplete_buffers
    for _ in range(3):
        cam.trigger()  # faster than the camera can expose: held back, not lost
    grabs = [_grab_retriggering(cam, 2.0) for _ in range(3)]
    counts = [int(frame.image[0, 0]) for frame, _ in grabs]
    lost = sum(n for _, n in grabs)
    assert lost == cam.incomplete_buffers - lost_before and scene.count == seen + 3 + lost
    assert counts == sorted(set(counts))
    assert lost > 0 or counts == [seen + 1, seen + 2, seen + 3]


def test_a_lost_packet_loses_its_frame_at_once_and_a_new_trigger_recovers(lossy) -> None:
    """Packets dropped on the link and not resent: the frame's buffer comes back
    incomplete and grab raises `FrameLost` right away (it used to wait for the grab
    timeout, then raise `CameraTimeout`); triggering again gives the next frame, and the
    stream statistics count the missing packets."""
    cam = lossy
    before = cam.stream_statistics()
    frames, lost = [], []
    for _ in range(200):  # until both outcomes were seen enough (about 15 triggers)
        cam.trigger()
        try:
            frames.append(cam.grab(30.0))  # a timeout this long would fail the test
        except FrameLost as exc:
            lost.append(str(exc))
        if len(frames) >= 5 and len(lost) >= 3:
            break
    assert len(frames) >= 5 and len(lost) >= 3
    assert "arrived incomplete" in lost[0] and "trigger again" in lost[0]
    assert all(0 < (b.sequence - a.sequence) % 65536 < 100 for a, b in pairwise(frames))
    stats = cam.stream_statistics().since(before)
    assert cam.incomplete_buffers == len(lost) == stats.incomplete_frames
    assert stats.completed_frames == len(frames) and stats.missing_packets >= len(lost)
    assert stats.received_packets > 0 and not stats.packet_resend  # the fake cannot resend
    total = cam.stream_statistics()
    cam.stop()  # the counts survive a stream restart
    assert cam.stream_statistics() == total


def test_back_to_back_triggers_survive_lost_packets(lossy) -> None:
    """Three triggers at once on a lossy link: each gives a frame or a `FrameLost`, and
    triggering again for each lost one ends with three good frames in order."""
    cam = lossy
    before = cam.stream_statistics()
    for _ in range(3):
        cam.trigger()
    grabs = [_grab_retriggering(cam, 30.0) for _ in range(3)]
    seqs = [frame.sequence for frame, _ in grabs]
    assert all(0 < (b - a) % 65536 < 100 for a, b in pairwise(seqs))
    assert sum(n for _, n in grabs) == cam.incomplete_buffers
    assert cam.stream_statistics().since(before).completed_frames == 3


def test_gige_stream_asks_for_resends_where_the_camera_offers_them(cam) -> None:
    """Packet resend follows the camera's capability (Aravis' fake has none, so it stays
    off); resend timings that leave no time for a resend are refused."""
    from acquisition.camera.aravis_camera import AravisCamera

    cam.configure(_software())
    cam.start()
    assert cam.stream_statistics().packet_resend is False
    with pytest.raises(DeviceSettingsError, match="packet_timeout_s < frame_retention_s"):
        AravisCamera("127.0.0.1", packet_timeout_s=0.2, frame_retention_s=0.1)
