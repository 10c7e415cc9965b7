"""Pattern plans: building, validation errors, JSON round trip, rendering to display codes."""

import itertools
import json

import numpy as np
import pytest

from acquisition.patterns import DisplayResponse, build_plan, choose_periods, render_frame
from api.cli import main
from calibration.shared.plan import PlanError, plan_from_dict, read_plan, write_plan


def test_default_plan_periods_cover_screen_and_ratio_bounded():
    plan = build_plan(1920, 1080, 0.25)
    for axis, extent in (("x", 1920), ("y", 1080)):
        sets = plan.period_sets(axis)
        periods = [s.period_px for s in sets]
        assert periods[0] >= extent
        assert all(a / b <= 8.0 + 1e-9 for a, b in itertools.pairwise(periods))
        assert all(s.steps == 8 and len(s.frame_indices) == 8 for s in sets)
    assert plan.flat_indices(1.0) == [0] and plan.flat_indices(0.0) == [1]


def test_choose_periods_single_when_finest_exceeds_extent():
    assert choose_periods(100, 500, 8) == [105.0]


def test_round_trip(tmp_path):
    plan = build_plan(800, 600, [0.2, 0.21], preset="fast")
    path = tmp_path / "plan.json"
    write_plan(plan, path)
    again = read_plan(path)
    assert again == plan
    assert again.digest() == plan.digest()


def _base():
    return build_plan(640, 480, 0.3).to_dict()


@pytest.mark.parametrize(
    ("mutate", "message"),
    [
        (lambda d: d["frames"][2].update(axis="z"), "unknown axis 'z'"),
        (lambda d: d["frames"][2].update(period_px=0), "period_px: must be > 0"),
        (lambda d: d["frames"][2].update(steps=2), "at least 3 phase steps"),
        (lambda d: d.pop("screen"), "screen: missing"),
        (lambda d: d["screen"].pop("pitch_mm"), "screen.pitch_mm: missing"),
        (lambda d: d.update(format="other/1"), "format: expected 'phasecal.plan/1'"),
        (lambda d: d["frames"].pop(3), "needs steps 0..7 exactly once"),
        (lambda d: d["frames"].pop(1), "dark flat frame"),
        (lambda d: d["frames"][2].update(kind="checker"), "unknown frame kind"),
    ],
)
def test_bad_plans_rejected_with_field(mutate, message):
    data = _base()
    mutate(data)
    with pytest.raises(PlanError, match=message):
        plan_from_dict(data)


def test_coarsest_must_cover_extent():
    with pytest.raises(PlanError, match="must cover the screen extent"):
        build_plan(640, 480, 0.3, periods_x=[300, 40])


def test_unknown_keys_ignored_and_kept():
    data = _base()
    data["sync_marker"] = {"size_px": 32}
    plan = plan_from_dict(data)
    assert plan.to_dict()["sync_marker"] == {"size_px": 32}


def test_render_8_and_10_bit_dtypes_and_range():
    plan = build_plan(64, 32, 0.3, periods_x=[100, 16], periods_y=[40])
    img8 = render_frame(plan, 2, bit_depth=8)
    img10 = render_frame(plan, 2, bit_depth=10)
    assert img8.dtype == np.uint8 and img8.shape == (32, 64)
    assert img10.dtype == np.uint16 and img10.max() <= 1023
    assert render_frame(plan, 0).min() == 255 and render_frame(plan, 1).max() == 0


def test_dithering_removes_systematic_quantization_error():
    """Low-contrast cosines seen through a camera's blur (8x8 box): plain rounding leaves a
    pattern-locked phase error; dithering (ordered or random) cuts the systematic part."""
    import cv2

    plan = build_plan(
        512, 64, 0.3, periods_x=[600, 75], periods_y=[70], steps=8, amplitude=0.012
    )
    pset = next(s for s in plan.period_sets("x") if s.period_px == 75)

    def phase(image_of):
        a = b = 0.0
        for k, idx in enumerate(pset.frame_indices):
            img = cv2.blur(image_of(idx), (8, 8))
            a = a + img * np.sin(2 * np.pi * k / pset.steps)
            b = b + img * np.cos(2 * np.pi * k / pset.steps)
        return np.arctan2(-a, b)[8:-8, 8:-8]

    from acquisition.patterns import frame_linear

    reference = phase(lambda i: frame_linear(plan, i) * 255)

    def systematic_error(dither):
        got = phase(lambda i: render_frame(plan, i, dither=dither).astype(np.float64))
        err = np.angle(np.exp(1j * (got - reference)))
        return np.abs(err.mean(axis=0)).max()  # column means: the pattern-locked part

    rounding = systematic_error(None)
    assert systematic_error("ordered") < 0.5 * rounding
    assert systematic_error("random") < 0.5 * rounding


def test_gamma_lut_precompensation():
    plan = build_plan(256, 16, 0.3, periods_x=[300], periods_y=[20])
    resp = DisplayResponse.gamma(2.2)
    img = render_frame(plan, 2, response=resp, dither=None)
    from acquisition.patterns import frame_linear

    emitted = (img / 255.0) ** 2.2
    assert np.abs(emitted - frame_linear(plan, 2)).max() < 0.02


def test_cli_plan_writes_and_rejects(tmp_path, capsys):
    out = tmp_path / "p.json"
    assert main(["plan", "--screen-width-px", "1024", "--screen-height-px", "768",
                 "--pitch-mm", "0.25", "-o", str(out)]) == 0
    data = json.loads(out.read_text())
    assert data["screen"]["width_px"] == 1024
    assert main(["plan", "--steps", "2", "-o", str(tmp_path / "bad.json")]) == 1
    assert "at least 3 phase steps" in capsys.readouterr().err
    assert not (tmp_path / "bad.json").exists()
