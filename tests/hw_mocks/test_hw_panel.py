"""hw_mocks' real screen: shaped panel behind cover glass, against closed-form optics."""

from __future__ import annotations

import numpy as np
import pytest

from calibration.shared.plan import ScreenGeometry
from hw_mocks.cameras import mild_pinhole
from hw_mocks.panel import PanelShape, lateral_shift_mm
from hw_mocks.poses import look_at_pose, random_poses
from hw_mocks.rig import SimulatedRig
from hw_mocks.scene import screen_points
from hw_mocks.synthetic import synthetic_maps

SCREEN = ScreenGeometry(640, 400, (0.25, 0.25))


def test_glass_shift_at_30_degrees_matches_snell() -> None:
    """A ray at 30 degrees through 1.5 mm of n = 1.52 glass lands ~0.34 mm short (PHYSICS 7)."""
    panel = PanelShape(glass_mm=1.5, glass_index=1.52)
    theta = np.radians(30.0)
    o = np.array([[10.0, 20.0, -100.0]])
    d = np.array([[np.sin(theta), 0.0, np.cos(theta)]])
    x, y, ok = panel.trace(SCREEN, o, d)
    bare_x = 10.0 + 100.0 * np.tan(theta)
    assert ok[0] and y[0] == pytest.approx(20.0)
    assert bare_x - x[0] == pytest.approx(lateral_shift_mm(theta, 1.5, 1.52), abs=1e-9)
    assert bare_x - x[0] == pytest.approx(0.344, abs=0.002)
    # Snell by hand: the path inside the glass makes theta' with the normal.
    inner = np.arcsin(np.sin(theta) / 1.52)
    assert x[0] == pytest.approx(10.0 + 98.5 * np.tan(theta) + 1.5 * np.tan(inner), abs=1e-9)


def test_ideal_panel_reproduces_todays_screen() -> None:
    """Zero thickness, flat: the same screen points as without a panel, bit for bit."""
    cam = mild_pinhole(80, 60)
    pose = look_at_pose(SCREEN, distance_mm=150.0, tilt_deg=20.0, tilt_azimuth_deg=30.0)
    x0, y0 = screen_points(cam, pose, SCREEN)
    x1, y1 = screen_points(cam, pose, SCREEN, panel=PanelShape())
    np.testing.assert_array_equal(x0, x1)
    np.testing.assert_array_equal(y0, y1)


def test_bow_depth_has_zero_mean_and_tilt_and_lies_on_the_panel() -> None:
    """The shape terms carry no plane (the pose's gauge); traced hits lie on the surface."""
    panel = PanelShape(bow_x_mm=0.5, bow_y_mm=0.3, twist_mm=0.2, glass_mm=1.5)
    xs = (np.arange(SCREEN.width_px) * SCREEN.pitch_mm[0])[None, :]
    ys = (np.arange(SCREEN.height_px) * SCREEN.pitch_mm[1])[:, None]
    z = panel.depth_mm(SCREEN, xs + 0 * ys, ys + 0 * xs)
    a = np.column_stack([np.ones(z.size), (xs + 0 * ys).ravel(), (ys + 0 * xs).ravel()])
    coef = np.linalg.lstsq(a, z.ravel(), rcond=None)[0]
    assert np.abs(coef).max() < 1e-4 * 0.5
    center = panel.depth_mm(SCREEN, np.array(79.875), np.array(49.875))
    edge = panel.depth_mm(SCREEN, np.array(-0.125), np.array(49.875))
    assert edge - center == pytest.approx(0.5, rel=1e-9)  # bow = center-to-edge sag
    rng = np.random.default_rng(1)
    o = np.column_stack([rng.uniform(0, 160, 50), rng.uniform(0, 100, 50), np.full(50, -200.0)])
    d = np.column_stack([rng.uniform(-0.5, 0.5, 50), rng.uniform(-0.5, 0.5, 50), np.ones(50)])
    x, y, ok = panel.trace(SCREEN, o, d)
    assert ok.all()
    # Back-trace: the point on the surface, refracted back out, lies on the incoming ray.
    zh = panel.depth_mm(SCREEN, x, y)
    q = d[:, :2] / d[:, 2:]
    m = q / np.sqrt(1.52**2 + (1.52**2 - 1) * np.sum(q * q, 1, keepdims=True))
    front = np.column_stack([x, y]) - (zh + 1.5)[:, None] * m
    np.testing.assert_allclose(front, o[:, :2] + (200.0 - 1.5) * q, atol=1e-9)


def test_bow_and_glass_move_seen_points_by_tenths_of_a_mm() -> None:
    """0.5/0.3 mm bow behind 1.5 mm glass shifts seen points by 0.1-0.6 mm RMS (PHYSICS 7)."""
    cam = mild_pinhole(64, 48)
    real = PanelShape(bow_x_mm=0.5, bow_y_mm=0.3, glass_mm=1.5)
    rng = np.random.default_rng(3)
    for pose in random_poses(cam, SCREEN, 4, rng, distance_mm=(120.0, 200.0)):
        x0, y0 = screen_points(cam, pose, SCREEN)
        x1, y1 = screen_points(cam, pose, SCREEN, panel=real)
        dmm = np.hypot(x1 - x0, y1 - y0) * 0.25
        rms = float(np.sqrt(np.nanmean(dmm**2)))
        assert 0.05 < rms < 1.0


def test_synthetic_maps_and_rig_use_the_panel() -> None:
    """Synthetic maps and the simulated rig's truth both see the shaped, glazed panel."""
    cam = mild_pinhole(48, 36)
    pose = look_at_pose(SCREEN, distance_mm=120.0, tilt_deg=25.0)
    real = PanelShape(bow_x_mm=0.5, bow_y_mm=0.3, glass_mm=1.5)
    maps, truth = synthetic_maps(cam, pose, SCREEN, sigma_px=0.0, rng=np.random.default_rng(0),
                                 panel=real)
    x_ref, _ = screen_points(cam, pose, SCREEN, panel=real)
    np.testing.assert_array_equal(maps.x, x_ref)
    assert truth["panel"] == real
    rig = SimulatedRig(cam, SCREEN, pose=pose, optics={"panel": real})
    np.testing.assert_allclose(rig.truth()["x_true"], x_ref)
    rig.set_pose(pose.rotation, pose.translation + np.array([0.0, 0.0, 10.0]))
    assert rig.truth()["panel"] == real


def test_panel_rejects_bad_fields() -> None:
    """Clear errors: negative glass, index below 1, a panel poking through its glass."""
    with pytest.raises(ValueError, match="glass_mm"):
        PanelShape(glass_mm=-1.0)
    with pytest.raises(ValueError, match="glass_index"):
        PanelShape(glass_mm=1.0, glass_index=0.9)
    with pytest.raises(ValueError, match="behind"):
        PanelShape(bow_x_mm=3.0, glass_mm=0.5)
