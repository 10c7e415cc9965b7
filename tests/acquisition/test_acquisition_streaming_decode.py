"""The controller streams accepted frames straight into the decoder (no stack is kept), and
the decoded maps agree with the simulator's ground truth within the predicted sigma."""

from __future__ import annotations

import numpy as np
import pytest

from acquisition.controller import capture_pose
from acquisition.patterns import build_plan
from acquisition.setup import measure_display_response
from calibration.decode import StreamingDecoder
from calibration.shared.plan import ScreenGeometry
from hw_mocks.cameras import mild_pinhole
from hw_mocks.rig import SimulatedRig

SCREEN = ScreenGeometry(320, 200, (0.5, 0.5))


class CountingDecoder(StreamingDecoder):
    """A StreamingDecoder that also records the order frames arrived in."""

    def __init__(self, *args, **kwargs) -> None:
        super().__init__(*args, **kwargs)
        self.order: list[int] = []

    def add(self, index: int, image: np.ndarray) -> None:
        self.order.append(index)
        super().add(index, image)


@pytest.mark.parametrize("mode", ["software", "free-running"])
def test_controller_streams_into_decoder_and_maps_match_truth(mode):
    rig = SimulatedRig(mild_pinhole(96, 72), SCREEN, display={"latency_periods": 2})
    settings = rig.with_settings(exposure_s=0.012, trigger_mode=mode,
                                 frame_rate_hz=30.0 if mode == "free-running" else None)
    # gamma pre-compensation from the display response measured through the camera
    rig.rig.display_response = measure_display_response(
        rig.display, rig.camera, rig.clock, settings, latency_s=2 / 60)
    plan = build_plan(SCREEN.width_px, SCREEN.height_px, SCREEN.pitch_mm)
    decoder = CountingDecoder(plan, (72, 96), noise=rig.sensor,
                              saturation_dn=rig.sensor.max_dn)
    result = capture_pose(rig.rig, plan, decoder, settings=settings)
    assert result.status == "complete", result.reason
    assert sorted(decoder.order) == list(range(len(plan.frames)))  # each frame exactly once
    maps = decoder.finish({"pose_id": "p0"})

    truth = rig.truth()
    valid = maps.mask & truth["visible"]
    assert valid.sum() > 0.5 * truth["visible"].sum()
    assert not (maps.mask & ~truth["visible_center"]).any()  # no screen seen -> invalid
    zx = (maps.x - truth["x_true"])[valid] / maps.sigma_x[valid]
    zy = (maps.y - truth["y_true"])[valid] / maps.sigma_y[valid]
    for z in (zx, zy):
        assert 0.7 < z.std() < 1.4
        assert abs(z.mean()) < 0.2
