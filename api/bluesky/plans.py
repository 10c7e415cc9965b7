"""A Bluesky plan that runs a whole phasecal calibration session with the devices of
`api.bluesky.devices`: screen poses from a list or from the service's guidance, one capture
per pose, then a calibration whose statistics are an event of the run, so the run's
documents (start, descriptors, events, stop) carry every pose and the result."""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import bluesky.plan_stubs as bps
import bluesky.preprocessors as bpp
from bluesky.utils import MsgGenerator
from ophyd_async.plan_stubs import ensure_connected

from api.bluesky.devices import (
    PhasecalCalibration,
    PhasecalCapture,
    PhasecalGuide,
    PhasecalScreen,
    ScreenPose,
    screen_pose_vectors,
)

CAPTURES = "primary"  # one event per pose: capture and screen readings
GUIDANCE = "guidance"  # one event per suggested pose
CALIBRATION = "calibration"  # one event: the fit's statistics


def calibration_session(capture: PhasecalCapture, screen: PhasecalScreen,
                        calibration: PhasecalCalibration,
                        poses: Sequence[ScreenPose] | None = None, *,
                        guide: PhasecalGuide | None = None, pose_count: int = 5,
                        heldout: int = 0, md: dict[str, Any] | None = None
                        ) -> MsgGenerator[str]:
    """Capture a pose at each screen pose and calibrate; returns the calibration id.

    The screen poses are either `poses` (each `{"rvec", "tvec_mm"}`) or
    `pose_count` suggestions of `guide` (starting poses, then the next-pose guidance), each
    read into the `guidance` stream before the screen moves there. The last `heldout`
    captured poses are held out of the fit and scored. Staging `capture` creates (or
    attaches) the session; its id is in the start document (`phasecal_session_id`).
    """
    if (poses is None) == (guide is None):
        raise ValueError("calibration_session: give either the screen poses or a guide that "
                         "plans them")
    listed = [dict(pose) for pose in poses or ()]
    for pose in listed:
        screen_pose_vectors(pose)  # a bad pose fails before anything moves
    count = len(listed) if poses is not None else pose_count
    if not 0 <= heldout < count:
        raise ValueError(f"calibration_session: heldout must be in [0, {count - 1}] for "
                         f"{count} poses, got {heldout}")
    devices = [d for d in (capture, screen, guide, calibration) if d is not None]
    yield from ensure_connected(*devices)
    calibration_ids: list[str] = []  # what the run made (run_wrapper returns the run's uid)

    def next_target(index: int) -> MsgGenerator[dict[str, Any]]:
        """The listed pose, or the guide's suggestion read into the guidance stream."""
        if guide is None:
            return listed[index]
        yield from bps.trigger_and_read([guide], name=GUIDANCE)
        rvec = yield from bps.rd(guide.rvec)
        tvec = yield from bps.rd(guide.tvec_mm)
        return {"rvec": list(rvec), "tvec_mm": list(tvec)}

    def captured_run() -> MsgGenerator[None]:
        pose_ids: list[str] = []
        for index in range(count):
            yield from bps.checkpoint()  # a resumed run captures this pose again
            target = yield from next_target(index)
            yield from bps.mv(screen, target)
            yield from bps.trigger_and_read([capture, screen], name=CAPTURES)
            pose_ids.append((yield from bps.rd(capture.pose_id)))
        yield from bps.checkpoint()
        split = len(pose_ids) - heldout
        yield from bps.mv(calibration.pose_ids, pose_ids[:split],
                          calibration.heldout_pose_ids, pose_ids[split:])
        yield from bps.trigger_and_read([calibration], name=CALIBRATION)
        calibration_ids.append((yield from bps.rd(calibration.calibration_id)))

    def staged() -> MsgGenerator[str]:
        session_id = yield from bps.rd(capture.session_id)
        model = yield from bps.rd(calibration.model)
        start = {"plan_name": "calibration_session", "phasecal_session_id": session_id,
                 "phasecal_model": model, "num_points": count,
                 "detectors": [capture.name, calibration.name], "motors": [screen.name],
                 **(md or {})}
        return (yield from bpp.run_wrapper(captured_run(), md=start))

    yield from bpp.stage_wrapper(staged(), devices)
    return calibration_ids[0]
