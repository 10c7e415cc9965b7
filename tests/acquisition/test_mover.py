"""Movers: the conformance kit on every backend (simulated arm, pan-tilt and linear stages,
the HTTP client against a served arm), refused and failing moves."""

from __future__ import annotations

import threading
from collections.abc import Iterator

import httpx
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from acquisition.mover import MoveRefused, MoverError, MoveTimeout, RobotPose
from acquisition.movers.conformance import check_mover
from acquisition.movers.http import HttpMover
from acquisition.movers.http_server import MoverServer
from acquisition.movers.stage import StageKinematics
from hw_mocks.arm import SimulatedArm, SimulatedStage

FAST = {"speed_mm_s": 2000.0, "speed_deg_s": 600.0, "settle_s": 0.01}


def _pose(rotvec_deg: tuple[float, float, float], t: tuple[float, float, float]) -> RobotPose:
    return RobotPose(Rotation.from_rotvec(np.radians(rotvec_deg)).as_matrix(), np.array(t))


ARM_REACHABLE = [_pose((0, 0, 0), (400, 0, 300)), _pose((10, -5, 20), (100, 200, 500)),
                 _pose((0, 30, 0), (250, -150, 350))]
ARM_UNREACHABLE = _pose((0, 0, 0), (2000, 0, 0))


@pytest.fixture
def arm() -> Iterator[SimulatedArm]:
    mover = SimulatedArm(rng=np.random.default_rng(1), **FAST)
    yield mover
    mover.close()


def test_simulated_arm_conforms(arm: SimulatedArm) -> None:
    check_mover(arm, ARM_REACHABLE, ARM_UNREACHABLE)


def test_simulated_arm_lands_with_its_stated_repeatability() -> None:
    arm = SimulatedArm(repeatability_mm=0.02, repeatability_deg=0.005, settle_s=0.0,
                       speed_mm_s=1e6, speed_deg_s=1e6, rng=np.random.default_rng(2))
    errors = []
    for k in range(60):
        target = ARM_REACHABLE[k % 3]
        assert arm.move_to(target, 1.0) is target  # the encoders report the command
        errors.append(arm.true_pose().translation_mm - target.translation_mm)
    assert 0.012 < np.std(errors) < 0.03


@pytest.mark.parametrize("kind", ["pan-tilt", "linear"])
def test_stages_conform(kind: str) -> None:
    if kind == "pan-tilt":
        kin = StageKinematics("pan-tilt", (0.0, 0.0, 200.0),
                              {"pan": (-90.0, 90.0), "tilt": (-30.0, 30.0)})
        reachable = [kin.pose_for({"pan": 40, "tilt": 20}), kin.pose_for({"pan": -30, "tilt": 0})]
        unreachable = kin.pose_for({"pan": 0, "tilt": 0}) @ _pose((0, 0, 0), (5, 0, 0))
        beyond = kin.pose_for({"pan": 100, "tilt": 0})
    else:
        kin = StageKinematics("linear", (0.0, 0.0, 0.0), {"travel": (0.0, 300.0)},
                              direction=(0.0, 1.0, 0.0))
        reachable = [kin.pose_for({"travel": 250}), kin.pose_for({"travel": 20})]
        unreachable = _pose((5, 0, 0), (0, 100, 0))
        beyond = kin.pose_for({"travel": 1000})
    stage = SimulatedStage(kin, **FAST)
    check_mover(stage, reachable, unreachable)
    with pytest.raises(MoveRefused, match="outside"):  # on the axes, beyond a limit
        stage.move_to(beyond, 1.0)


def test_http_mover_conforms_against_a_served_arm(arm: SimulatedArm) -> None:
    server = MoverServer(arm)
    client = HttpMover(server.url)
    try:
        assert client.info == arm.info
        check_mover(client, ARM_REACHABLE, ARM_UNREACHABLE)
        with pytest.raises(MoveRefused, match="outside the workspace"):
            client.move_to(ARM_UNREACHABLE, 1.0)
    finally:
        client.close()
        server.close()


def test_http_mover_stops_a_robot_whose_server_does_not_answer_in_time() -> None:
    """A server that never answers the move: the client gives up at its timeout and sends
    /stop, which the robot gets."""
    stops = threading.Event()
    info = SimulatedArm().info.to_json()

    def handler(request: httpx.Request) -> httpx.Response:
        if request.url.path == "/move":
            raise httpx.ReadTimeout("no answer", request=request)
        if request.url.path == "/stop":
            stops.set()
            return httpx.Response(200, json={})
        return httpx.Response(200, json=info)

    client = HttpMover("http://robot.test", transport=httpx.MockTransport(handler))
    with pytest.raises(MoveTimeout, match="sent stop"):
        client.move_to(ARM_REACHABLE[0], 0.5)
    assert stops.is_set()


def test_http_mover_names_an_unreachable_server() -> None:
    def handler(request: httpx.Request) -> httpx.Response:
        raise httpx.ConnectError("connection refused", request=request)

    with pytest.raises(MoverError, match=r"robot server http://robot\.test/info"):
        HttpMover("http://robot.test", transport=httpx.MockTransport(handler))


def test_closed_arm_refuses_to_move(arm: SimulatedArm) -> None:
    arm.close()
    with pytest.raises(MoverError, match="closed"):
        arm.move_to(ARM_REACHABLE[0], 1.0)
