"""The mover conformance kit: checks every `Mover` backend must pass.

Like `acquisition/conformance.py` for displays and cameras, shipped with the code so a new
backend is checked the same way: `check_mover(mover, reachable, unreachable)` raises
AssertionError naming the broken rule. Used for the simulated arm and stages and for the
HTTP client against a served simulated arm.
"""

from __future__ import annotations

import re
import threading
import time
from collections.abc import Iterator, Sequence
from contextlib import contextmanager

from acquisition.mover import Mover, MoveRefused, MoveStopped, MoveTimeout, RobotPose

# A reached pose may differ from the request by this many stated 1-sigma repeatabilities.
_REACH_SIGMAS = 6.0


def check_mover(mover: Mover, reachable: Sequence[RobotPose], unreachable: RobotPose,
                *, timeout_s: float = 30.0) -> None:
    """`reachable` (>= 2 poses, the first two far enough apart that moving between them
    takes more than 10 ms) are reached and reported; `unreachable` is refused without
    moving; a too-short timeout and `stop()` from another thread halt the mover."""
    info = mover.info
    assert info.name and info.axes, "info must name the mover and its axes"
    assert info.repeatability_mm >= 0 and info.repeatability_deg >= 0
    assert len(reachable) >= 2, "check_mover needs two reachable poses"
    for pose in reachable:
        assert info.workspace.why_unreachable(pose) is None, "a reachable pose outside the " \
            "workspace the mover states"
        reported = mover.move_to(pose, timeout_s)
        assert reported.distance_mm(pose) <= _REACH_SIGMAS * info.repeatability_mm + 1e-6, \
            f"reported pose {reported.distance_mm(pose):.4g} mm from the request"
        assert reported.angle_to_deg(pose) <= _REACH_SIGMAS * info.repeatability_deg + 1e-6, \
            f"reported pose {reported.angle_to_deg(pose):.4g} deg from the request"
        now = mover.current_pose()
        assert now.distance_mm(reported) < 1e-9 and now.angle_to_deg(reported) < 1e-6, \
            "current_pose() differs from the pose move_to reported"
    before = mover.current_pose()
    with _raises(MoveRefused):
        mover.move_to(unreachable, timeout_s)
    assert mover.current_pose().distance_mm(before) < 1e-9, "a refused move moved the mover"
    with _raises(ValueError, match="timeout"):
        mover.move_to(reachable[0], 0.0)
    mover.stop()  # idle: harmless
    far, near = reachable[0], reachable[1]
    mover.move_to(near, timeout_s)
    with _raises(MoveTimeout):
        mover.move_to(far, 1e-3)
    _assert_still(mover, "after a timed-out move")
    _check_stop(mover, far, timeout_s)
    reported = mover.move_to(near, timeout_s)  # usable again after a stop
    assert reported.distance_mm(near) <= _REACH_SIGMAS * info.repeatability_mm + 1e-6


def _assert_still(mover: Mover, when: str) -> None:
    first = mover.current_pose()
    time.sleep(0.05)
    assert mover.current_pose().distance_mm(first) < 1e-9, f"the mover still moves {when}"


def _check_stop(mover: Mover, target: RobotPose, timeout_s: float) -> None:
    """stop() from another thread ends a move in progress with MoveStopped."""
    outcome: list[BaseException | RobotPose] = []

    def move() -> None:
        try:
            outcome.append(mover.move_to(target, timeout_s))
        except Exception as exc:
            outcome.append(exc)

    worker = threading.Thread(target=move)
    worker.start()
    deadline = time.monotonic() + timeout_s
    while worker.is_alive() and time.monotonic() < deadline:  # until one stop lands mid-move
        mover.stop()
        worker.join(0.002)
    assert not worker.is_alive(), "stop() did not end the move"
    assert outcome and isinstance(outcome[0], MoveStopped), \
        f"a stopped move must raise MoveStopped, got {outcome[:1]}"
    _assert_still(mover, "after stop()")


@contextmanager
def _raises(expected: type[BaseException], match: str | None = None) -> Iterator[None]:
    """Assert that the block raises `expected` (with `match` in its message)."""
    try:
        yield
    except expected as exc:
        if match is not None and not re.search(match, str(exc)):
            raise AssertionError(f"{type(exc).__name__} without {match!r}: {exc}") from exc
        return
    raise AssertionError(f"expected {expected.__name__} to be raised")
