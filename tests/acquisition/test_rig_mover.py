"""A mover in the rig config: each backend's section validated with clear errors, the rig's
`mover` built from it (simulated ones by the simulator factory, a robot server over HTTP by
acquisition itself), moves through the rig within its timeout, closed with the rig."""

from __future__ import annotations

import socket
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest

from acquisition.errors import AcquisitionError
from acquisition.mover import MoveRefused, MoverError, MoveTimeout, RobotPose
from acquisition.movers.http import HttpMover
from acquisition.movers.http_server import MoverServer
from acquisition.rig import RigConfigError, load_rig_config, open_rig, parse_rig_config
from hw_mocks.arm import SimulatedArm, SimulatedStage
from hw_mocks.rig import open_simulated_rig

FAST = {"speed_mm_s": 5000.0, "speed_deg_s": 2000.0, "settle_s": 0.0}
SMALL = {"kind": "simulated", "camera": {"width": 32, "height": 24}}
TARGET = RobotPose(np.eye(3), np.array([400.0, 0.0, 300.0]))


def _open(mover: dict) -> object:
    return open_rig(parse_rig_config({**SMALL, "mover": mover}), simulator=open_simulated_rig)


def test_a_toml_mover_section_is_read(tmp_path: Path) -> None:
    path = tmp_path / "rig.toml"
    path.write_text('kind = "simulated"\n[mover]\nbackend = "simulated-pan-tilt"\n'
                    'origin_mm = [0, 0, 200]\npan_deg = [-60, 60]\ntimeout_s = 12.5\n')
    mover = load_rig_config(path).mover
    assert mover.backend == "simulated-pan-tilt" and mover.pan_deg == (-60.0, 60.0)
    assert mover.tilt_deg == (-45.0, 45.0) and mover.timeout_s == 12.5


@pytest.mark.parametrize(("mover", "message"), [
    ({"backend": "robot"}, "mover: Input tag 'robot'"),
    ({"backend": "http"}, "mover.http.url: Field required"),
    ({"backend": "http", "url": "robot.lab:8100"}, "expected an http:// or https:// URL"),
    ({"backend": "simulated-arm", "timeout_s": 0}, "mover.simulated-arm.timeout_s"),
    ({"backend": "simulated-arm", "speed": 3}, "mover.simulated-arm.speed: Extra inputs"),
    ({"backend": "simulated-arm", "workspace": {"min_mm": [0, 0, 0], "max_mm": [1, -1, 1]}},
     "y of min_mm/max_mm: low 0 exceeds high -1"),
    ({"backend": "simulated-pan-tilt", "pan_deg": [30, -30]}, "pan_deg: low 30 exceeds"),
    ({"backend": "simulated-pan-tilt", "tilt_deg": [-120, 0]}, "tilt_deg within [-90, 90]"),
    ({"backend": "simulated-linear", "direction": [0, 0, 0]}, "direction: must not be zero"),
])
def test_invalid_mover_sections_are_refused_naming_the_field(mover: dict, message: str) -> None:
    with pytest.raises(RigConfigError, match="mover") as err:
        parse_rig_config({**SMALL, "mover": mover}, "rig.toml")
    assert message in str(err.value) and str(err.value).startswith("rig.toml: ")


def test_a_hardware_rig_cannot_have_a_simulated_mover() -> None:
    with pytest.raises(RigConfigError, match="'simulated-arm' is for simulated rigs"):
        parse_rig_config({"kind": "hardware", "screen": {"pitch_mm": 0.25},
                          "display": {"backend": "sdl"}, "camera": {"backend": "opencv"},
                          "mover": {"backend": "simulated-arm"}})


def test_a_rig_with_a_simulated_arm_moves_through_its_mover() -> None:
    rig = _open({"backend": "simulated-arm", "timeout_s": 5, "repeatability_mm": 0.01,
                 "workspace": {"min_mm": [-500, -500, 0], "max_mm": [500, 500, 800]}, **FAST})
    arm = rig.mover
    assert isinstance(arm, SimulatedArm) and rig.move_timeout_s == 5
    assert arm.info.repeatability_mm == 0.01 and arm.info.workspace.max_mm == (500, 500, 800)
    assert rig.move_to(TARGET) is TARGET and arm.moves == 1
    assert np.linalg.norm(arm.true_pose().translation_mm - TARGET.translation_mm) < 0.1
    with pytest.raises(MoveRefused, match=r"x = 900\.000 mm is outside the workspace"):
        rig.move_to(RobotPose(np.eye(3), np.array([900.0, 0.0, 300.0])))
    assert arm.current_pose() is TARGET  # a refused move moves nothing
    rig.close()
    with pytest.raises(MoverError, match="closed"):  # closed with the rig
        arm.move_to(TARGET, 1.0)


def test_a_stage_rig_refuses_poses_off_its_axes_and_a_slow_move_times_out() -> None:
    rig = _open({"backend": "simulated-linear", "travel_mm": [0, 500], "timeout_s": 0.05,
                 "speed_mm_s": 100.0, "settle_s": 0.0})
    try:
        assert isinstance(rig.mover, SimulatedStage) and rig.mover.info.axes == ("travel",)
        with pytest.raises(MoveRefused, match="a linear stage only translates"):
            rig.move_to(RobotPose(np.array([[0.0, -1, 0], [1, 0, 0], [0, 0, 1]]), np.zeros(3)))
        with pytest.raises(MoveTimeout, match=r"0\.05 s timeout"):  # 400 mm at 100 mm/s
            rig.move_to(RobotPose(np.eye(3), np.array([400.0, 0.0, 0.0])))
    finally:
        rig.close()


def test_a_rig_without_a_mover_says_so() -> None:
    rig = open_rig(parse_rig_config(SMALL), simulator=open_simulated_rig)
    try:
        assert rig.mover is None
        with pytest.raises(AcquisitionError, match="no mover: add a `mover` section"):
            rig.move_to(TARGET)
    finally:
        rig.close()


@pytest.fixture
def robot_server() -> Iterator[tuple[MoverServer, SimulatedArm]]:
    arm = SimulatedArm(rng=np.random.default_rng(3), **FAST)
    server = MoverServer(arm)
    yield server, arm
    server.close()
    arm.close()


def test_a_rig_reaches_a_robot_server_over_http(robot_server) -> None:
    server, arm = robot_server
    rig = _open({"backend": "http", "url": server.url, "timeout_s": 5})
    try:
        assert isinstance(rig.mover, HttpMover) and rig.mover.info.name == "simulated arm"
        reached = rig.move_to(TARGET)
        assert reached.distance_mm(TARGET) < 1e-9 and arm.moves == 1
        with pytest.raises(MoveRefused, match=r"robot server .*outside the workspace"):
            rig.move_to(RobotPose(np.eye(3), np.array([2000.0, 0.0, 0.0])))
    finally:
        rig.close()


def test_an_unreachable_robot_server_fails_the_rig_open() -> None:
    with socket.socket() as s:  # a port nothing listens on
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    with pytest.raises(MoverError, match=f"robot server http://127.0.0.1:{port}/info"):
        _open({"backend": "http", "url": f"http://127.0.0.1:{port}", "request_timeout_s": 2})
