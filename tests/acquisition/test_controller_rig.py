"""The controller on a simulated rig of several cameras: one screen, every pattern shown once,
each camera's frames checked by time against the simulator's ground truth."""

from __future__ import annotations

import pytest

from acquisition.controller import ControllerOptions, capture_rig_pose
from acquisition.patterns import build_plan
from acquisition.rig import parse_rig_config
from acquisition.sinks import MemoryFrameStore
from hw_mocks.rig import SimulatedRig, open_simulated_rig

PLAN = build_plan(320, 200, 0.5)
OPTIONS = ControllerOptions(latency_s=2 / 60)


def three_cameras(**overrides: dict) -> SimulatedRig:
    """Three cameras of different sizes, lenses and timing around one 320x200 screen."""
    cameras = [
        {"name": "left", "width": 80, "height": 60, "timestamp_jitter_s": 2e-4},
        {"name": "right", "width": 96, "height": 72, "trigger_latency_s": 1.5e-3,
         "timestamp_jitter_s": 4e-4, "readout_s": 8e-3},
        {"name": "top", "model": "smooth_noncentral", "width": 64, "height": 48,
         "trigger_latency_s": 5e-4, "timestamp_jitter_s": 1e-4},
    ]
    for cam in cameras:
        cam.update(overrides.get(cam["name"], {}))
    config = {"screen": {"width_px": 320, "height_px": 200, "pitch_mm": 0.5},
              "display": {"latency_periods": 2},
              "settings": {"exposure_s": 0.008, "trigger_mode": "software"},
              "cameras": cameras}
    sim = open_simulated_rig(parse_rig_config(config)).simulated
    assert isinstance(sim, SimulatedRig)
    sim.display.history_s = 1e9  # every shown image kept, for the checks against truth
    return sim


def mis_synced(sim: SimulatedRig, name: str, res) -> list[int]:
    """A camera's accepted frames whose exposure did not see exactly the image flipped for
    them (its own ground truth)."""
    flips = {h.image_id: h.flip_s for h in sim.display.history()}
    camera = sim.cameras[name]
    return [i for i, info in res.frames.items()
            if not camera.truth[info.sequence].pure
            or flips[camera.truth[info.sequence].image_ids[0]] != info.flip_s]


def shows(sim: SimulatedRig) -> int:
    return sum(1 for h in sim.display.history() if h.image_id > 0)


def test_three_cameras_capture_every_pattern_once_in_sync() -> None:
    sim = three_cameras()
    stores = {name: MemoryFrameStore() for name in sim.cameras}
    res = capture_rig_pose(sim.rig, PLAN, stores, options=OPTIONS)
    assert res.status == "complete", res.reason
    assert list(res.cameras) == ["left", "right", "top"] and res.recaptures == []
    assert shows(sim) == len(PLAN.frames) + 3  # each pattern once, plus the 3 references
    for name, store in stores.items():
        cam = res.cameras[name]
        assert sorted(store.frames) == list(range(len(PLAN.frames)))
        info = sim.cameras[name].info
        assert store.frames[0].shape == (info.height, info.width)
        assert mis_synced(sim, name, cam) == [], name
        assert cam.integrity is not None and cam.integrity.ok
    assert sorted(res.accepted) == list(range(len(PLAN.frames)))


def test_free_running_and_triggered_cameras_matched_by_timestamps() -> None:
    sim = three_cameras()
    stores = {name: MemoryFrameStore() for name in sim.cameras}
    running = sim.rig.settings_for("right").__class__(
        exposure_s=0.008, pixel_format="Mono12", trigger_mode="free-running", frame_rate_hz=30.0)
    res = capture_rig_pose(sim.rig, PLAN, stores, options=OPTIONS, settings={"right": running})
    assert res.status == "complete", res.reason
    for name in stores:
        assert len(stores[name].frames) == len(PLAN.frames)
        assert mis_synced(sim, name, res.cameras[name]) == [], name


def test_a_frame_dropped_by_one_camera_is_shown_again_for_it_alone() -> None:
    """The right camera's 7th triggered frame arrives incomplete: that pattern is shown again
    later, only the right camera takes it (a second hand-off to another camera's store
    would raise), and every camera's frames end complete and in sync."""
    sim = three_cameras()
    sim.drop_frame("right", 7)
    stores = {name: MemoryFrameStore() for name in sim.cameras}
    res = capture_rig_pose(sim.rig, PLAN, stores, options=OPTIONS)
    assert res.status == "complete", res.reason
    assert [(rc.camera, rc.reason.split(":")[0]) for rc in res.recaptures] == [("right", "lost")]
    assert res.cameras["right"].lost_frames == 1 and res.lost_frames == 1
    assert res.counters()["cameras"]["right"]["lost_frames"] == 1
    assert shows(sim) == len(PLAN.frames) + 3 + 1
    again = res.recaptures[0].index
    assert res.cameras["right"].accepted[-1] == again  # shown again after the others
    assert res.cameras["left"].accepted.count(again) == 1
    for name, store in stores.items():
        assert sorted(store.frames) == list(range(len(PLAN.frames)))
        assert mis_synced(sim, name, res.cameras[name]) == [], name


def test_a_camera_that_keeps_losing_frames_fails_the_pose_naming_it() -> None:
    sim = three_cameras(top={"lost_triggers": list(range(1, 1000))})
    res = capture_rig_pose(sim.rig, PLAN, {n: MemoryFrameStore() for n in sim.cameras},
                           options=ControllerOptions(latency_s=2 / 60, max_attempts=3))
    assert res.status == "failed" and "on camera 'top'" in res.reason
    assert "after 3 attempts" in res.reason
    assert all(r.status == "failed" for r in res.cameras.values())


def test_unknown_camera_is_refused() -> None:
    sim = three_cameras()
    with pytest.raises(ValueError, match=r"unknown camera\(s\) \['back'\]"):
        capture_rig_pose(sim.rig, PLAN, {"back": MemoryFrameStore()}, options=OPTIONS)
