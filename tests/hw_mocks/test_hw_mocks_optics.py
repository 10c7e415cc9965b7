"""Ground-truth cameras, scene geometry, image formation and sensor of the simulated rig."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from acquisition.patterns import DisplayResponse, build_plan
from calibration.shared.maps import load_maps
from calibration.shared.plan import CosineFrame, Plan, ScreenGeometry
from hw_mocks.cameras import (
    EquidistantFisheye,
    NonCentralCamera,
    PinholeCamera,
    TruthCamera,
    make_truth_camera,
    mild_pinhole,
    smooth_noncentral,
    wide_fisheye,
)
from hw_mocks.fisheye_camera import fisheye_theta_d
from hw_mocks.optics import OpticalSetup
from hw_mocks.poses import (
    coverage,
    look_at_pose,
    random_poses,
    rotation_about,
    rotation_only_poses,
)
from hw_mocks.scene import ScreenPose, screen_points, screen_points_at
from hw_mocks.sensor import SensorModel
from hw_mocks.synthetic import render_plan_frames, synthetic_maps

W, H = 160, 120
SCREEN = ScreenGeometry(640, 360, (0.8, 0.8))

CAMERAS = {
    "pinhole": lambda: mild_pinhole(W, H),
    "rational": lambda: PinholeCamera(
        W, H, 140.0, 141.0, 81.0, 58.5, (0.3, -0.05, 1e-3, -5e-4, 0.01, 0.35, -0.04, 0.02)
    ),
    "fisheye": lambda: wide_fisheye(W, H),
    "noncentral": lambda: smooth_noncentral(W, H),
    "noncentral_bumps": lambda: smooth_noncentral(W, H, bumps=True),
    "noncentral_fisheye": lambda: NonCentralCamera(wide_fisheye(W, H, fov_deg=170.0)),
}


def _decode(frames: np.ndarray, steps: int) -> tuple[np.ndarray, np.ndarray]:
    """docs/physics.md section 1: wrapped phase and modulation of an N-step stack."""
    psi = 2 * np.pi * np.arange(steps) / steps
    a = np.tensordot(np.sin(psi), frames, axes=1)
    b = np.tensordot(np.cos(psi), frames, axes=1)
    return np.arctan2(-a, b), 2.0 / steps * np.hypot(a, b)


def _wrap_px(phase: np.ndarray, x_true: np.ndarray, period: float) -> np.ndarray:
    """Decoded minus true position (screen px), wrapped into one period."""
    d = phase - 2 * np.pi * x_true / period
    return np.angle(np.exp(1j * d)) * period / (2 * np.pi)


def _cosine_plan(period: float, steps: int, screen: ScreenGeometry = SCREEN) -> Plan:
    """A plan of one x-axis period (no flats)."""
    frames = tuple(CosineFrame("x", period, k, steps) for k in range(steps))
    return Plan(screen, frames)


def _frontal_setup(camera: TruthCamera, **kw) -> OpticalSetup:
    """The screen frontal and close enough to fill the whole image."""
    pose = look_at_pose(SCREEN, distance_mm=200.0)
    return OpticalSetup(camera, pose, SCREEN, **kw)


# -- cameras -------------------------------------------------------------------------


@pytest.mark.parametrize("name", list(CAMERAS))
def test_rays_project_round_trip(name: str) -> None:
    cam = CAMERAS[name]()
    u, v = cam.pixel_grid()
    o, d = cam.rays(u, v)
    ok = np.isfinite(d[..., 0])
    assert ok.mean() > 0.85
    np.testing.assert_allclose(np.linalg.norm(d[ok], axis=-1), 1.0, atol=1e-12)
    for dist in (50.0, 2000.0):
        uv = cam.project(o[ok] + dist * d[ok])
        err = np.hypot(uv[:, 0] - u[ok], uv[:, 1] - v[ok])
        assert np.all(np.isfinite(err))
        assert err.max() < 1e-8
    assert cam.is_central == (not name.startswith("noncentral"))


def test_pinhole_matches_opencv_projection() -> None:
    cam = CAMERAS["rational"]()
    rng = np.random.default_rng(0)
    pts = np.column_stack([rng.uniform(-0.5, 0.5, (300, 2)), np.ones(300)]) * rng.uniform(
        10, 900, (300, 1)
    )
    mine = cam.project(pts)
    ref, _ = cv2.projectPoints(
        pts.reshape(-1, 1, 3), np.zeros(3), np.zeros(3), cam.camera_matrix, np.asarray(cam.dist)
    )
    ok = np.isfinite(mine[:, 0])
    assert ok.sum() > 150
    np.testing.assert_allclose(mine[ok], ref.reshape(-1, 2)[ok], atol=1e-9)


def test_fisheye_matches_opencv_and_sees_75_degrees_at_edge() -> None:
    cam = wide_fisheye(W, H, fov_deg=150.0)
    _, d = cam.rays(np.array([-0.5, W - 0.5]), np.full(2, cam.cy))
    angles = np.degrees(np.arccos(d[:, 2]))
    assert np.nanmax(angles) == pytest.approx(75.0, abs=0.01)
    assert np.nanmin(angles) > 72.0
    rng = np.random.default_rng(1)
    dirs = rng.normal(size=(400, 3))
    dirs[:, 2] = np.abs(dirs[:, 2]) + 0.3
    mine = cam.project(dirs * 100.0)
    k = np.array([[cam.f, 0, cam.cx], [0, cam.f, cam.cy], [0, 0, 1.0]])
    ref, _ = cv2.fisheye.projectPoints(
        (dirs * 100.0).reshape(1, -1, 3), np.zeros(3), np.zeros(3), k, np.asarray(cam.k)
    )
    ok = np.isfinite(mine[:, 0])
    assert ok.sum() > 100
    np.testing.assert_allclose(mine[ok], ref.reshape(-1, 2)[ok], atol=1e-8)
    # Beyond the 75 degree half-FOV nothing is imaged, even inside the sensor.
    behind = np.array([[np.sin(np.radians(80.0)), 0.0, np.cos(np.radians(80.0))]])
    assert np.all(np.isnan(cam.project(behind)))


def test_fisheye_polynomial_and_its_derivative() -> None:
    theta = np.linspace(0.0, 1.3, 27)
    td, der = fisheye_theta_d((0.0, 0.0, 0.0, 0.0), theta)
    np.testing.assert_array_equal(td, theta)  # no distortion: r = f theta
    np.testing.assert_array_equal(der, 1.0)
    k = (0.012, -0.004, 0.0008, -0.0001)
    td, der = fisheye_theta_d(k, theta)
    t = theta[3]
    assert td[3] == pytest.approx(t * (1 + k[0] * t**2 + k[1] * t**4 + k[2] * t**6 + k[3] * t**8))
    h = 1e-6
    numeric = (fisheye_theta_d(k, theta + h)[0] - fisheye_theta_d(k, theta - h)[0]) / (2 * h)
    np.testing.assert_allclose(der, numeric, rtol=1e-8)


def test_rotation_about_an_axis_is_right_handed_and_proper() -> None:
    quarter = rotation_about(np.array([0.0, 0.0, 5.0]), np.pi / 2)  # axis length is irrelevant
    np.testing.assert_allclose(quarter @ [1.0, 0, 0], [0, 1.0, 0], atol=1e-15)
    axis = np.array([1.0, -2.0, 0.5])
    r = rotation_about(axis, 0.7)
    np.testing.assert_allclose(r @ r.T, np.eye(3), atol=1e-15)
    assert np.linalg.det(r) == pytest.approx(1.0)
    np.testing.assert_allclose(r @ axis, axis, atol=1e-15)
    assert np.degrees(np.arccos((np.trace(r) - 1) / 2)) == pytest.approx(np.degrees(0.7))


def test_project_rejects_points_not_imaged() -> None:
    cam = mild_pinhole(W, H)
    pts = np.array([[0.0, 0.0, -100.0], [1000.0, 0.0, 10.0], [0.0, 0.0, 100.0]])
    uv = cam.project(pts)
    assert np.isnan(uv[:2]).all() and np.isfinite(uv[2]).all()
    with pytest.raises(ValueError, match="points"):
        cam.project(np.zeros((4, 2)))
    with pytest.raises(ValueError, match="dist"):
        PinholeCamera(W, H, 100, 100, 80, 60, (0.1, 0.2, 0.3))


def test_named_truth_cameras() -> None:
    cam = make_truth_camera("wide_fisheye", 64, 48, fov_deg=120.0)
    assert isinstance(cam, EquidistantFisheye) and (cam.width, cam.height) == (64, 48)
    assert make_truth_camera("smooth_noncentral", 64, 48).is_central is False
    with pytest.raises(ValueError, match="unknown truth camera 'nope'"):
        make_truth_camera("nope", 64, 48)
    with pytest.raises(ValueError, match="bad parameters"):
        make_truth_camera("mild_pinhole", 64, 48, fov_deg=3.0)


def test_noncentral_deviates_smoothly_from_its_base() -> None:
    cam = smooth_noncentral(W, H, bumps=True)
    u, v = cam.pixel_grid()
    o, d = cam.rays(u, v)
    _, d0 = cam.base.rays(u, v)
    angle = np.arccos(np.clip(np.sum(d * d0, axis=-1), -1, 1))
    assert 2e-4 < np.median(angle) < 3e-3 and angle.max() < 6e-3
    spread = np.linalg.norm(o - o.reshape(-1, 3).mean(0), axis=-1)
    assert 0.02 < spread.max() < 1.0  # a fraction of a millimetre: truly non-central
    plain = smooth_noncentral(W, H, bumps=False)
    _, dp = plain.rays(u, v)
    bump = np.arccos(np.clip(np.sum(d * dp, axis=-1), -1, 1))
    assert bump.max() > 5e-4  # the bumps add local deviations
    assert np.median(bump) < 1e-5  # ... and only locally


# -- scene and poses ---------------------------------------------------------------


@pytest.mark.parametrize("name", ["pinhole", "fisheye", "noncentral"])
def test_screen_points_match_direct_ray_plane_intersection(name: str) -> None:
    cam = CAMERAS[name]()
    pose = random_poses(cam, SCREEN, 1, np.random.default_rng(4))[0]
    x, y = screen_points(cam, pose, SCREEN)
    u, v = cam.pixel_grid()
    o, d = cam.rays(u, v)
    n = pose.rotation[:, 2]
    lam = ((pose.translation - o) @ n) / (d @ n)
    hit = o + lam[..., None] * d
    s = (hit - pose.translation) @ pose.rotation
    xs, ys = s[..., 0] / SCREEN.pitch_mm[0], s[..., 1] / SCREEN.pitch_mm[1]
    inside = (lam > 0) & (xs >= -0.5) & (xs <= 639.5) & (ys >= -0.5) & (ys <= 359.5)
    assert np.array_equal(np.isfinite(x), inside)
    assert inside.mean() > 0.3
    np.testing.assert_allclose(x[inside], xs[inside], atol=1e-9)
    np.testing.assert_allclose(y[inside], ys[inside], atol=1e-9)
    # Projecting the seen screen points gives back the pixels.
    pts = pose.screen_px_to_camera(SCREEN, x[inside], y[inside])
    uv = cam.project(pts)
    np.testing.assert_allclose(uv[:, 0], u[inside], atol=1e-7)
    np.testing.assert_allclose(uv[:, 1], v[inside], atol=1e-7)


def test_screen_points_supersample_layout_and_misses() -> None:
    cam = mild_pinhole(W, H)
    pose = look_at_pose(SCREEN, distance_mm=300.0)
    xs, _ = screen_points(cam, pose, SCREEN, supersample=3)
    assert xs.shape == (3 * H, 3 * W)
    x1, _ = screen_points_at(cam, pose, SCREEN, np.array([10.0 + 1 / 3]), np.array([20.0 - 1 / 3]))
    assert xs[20 * 3, 10 * 3 + 2] == pytest.approx(x1[0], abs=1e-9)
    # Screen behind the camera, and screen seen from its back side: nothing visible.
    behind = ScreenPose(pose.rotation, pose.translation * np.array([1, 1, -1]))
    flipped_rot = pose.rotation @ np.diag([1.0, -1.0, -1.0])
    back = ScreenPose(flipped_rot, pose.translation - flipped_rot @ [0, 0, 0])
    for p in (behind, back):
        assert np.isnan(screen_points(cam, p, SCREEN)[0]).all()


def test_random_poses_are_varied_and_cover_the_image() -> None:
    cam = wide_fisheye(W, H)
    poses = random_poses(cam, SCREEN, 6, np.random.default_rng(7), min_coverage=0.35)
    normals = np.array([p.rotation[:, 2] for p in poses])
    assert all(coverage(cam, p, SCREEN) >= 0.35 for p in poses)
    tilts = np.degrees(np.arccos(normals[:, 2]))
    assert tilts.max() - tilts.min() > 5.0 and len({tuple(np.round(n, 6)) for n in normals}) == 6
    seen = np.zeros((H, W), bool)
    for p in poses:
        seen |= np.isfinite(screen_points(cam, p, SCREEN)[0])
    assert seen.mean() > 0.8  # together the poses cover most of the image
    with pytest.raises(ValueError, match="coverage"):
        random_poses(cam, SCREEN, 1, np.random.default_rng(0), distance_mm=1e5)


def test_rotation_only_poses_share_the_camera_center() -> None:
    cam = mild_pinhole(W, H)
    poses = rotation_only_poses(cam, SCREEN, 4, np.random.default_rng(2), max_rotation_deg=10)
    centers = np.array([-p.rotation.T @ p.translation for p in poses])  # camera in screen frame
    np.testing.assert_allclose(centers - centers[0], 0.0, atol=1e-9)
    for p in poses[1:]:
        q = p.rotation @ poses[0].rotation.T
        angle = np.degrees(np.arccos(np.clip((np.trace(q) - 1) / 2, -1, 1)))
        assert 2.0 < angle <= 10.0 + 1e-9
        assert coverage(cam, p, SCREEN) >= 0.3


def test_pose_rvec_round_trip() -> None:
    pose = look_at_pose(SCREEN, distance_mm=400.0, tilt_deg=25, tilt_azimuth_deg=40, roll_deg=7)
    again = ScreenPose.from_rvec(pose.rvec, pose.translation)
    np.testing.assert_allclose(again.rotation, pose.rotation, atol=1e-12)
    with pytest.raises(ValueError, match="rotation"):
        ScreenPose(np.diag([1.0, 1.0, -1.0]), np.zeros(3))


# -- optics ------------------------------------------------------------------------


def test_rendered_cosine_decodes_to_truth_without_bias() -> None:
    cam = mild_pinhole(W, H)
    pose = random_poses(cam, SCREEN, 1, np.random.default_rng(11))[0]
    setup = OpticalSetup(cam, pose, SCREEN, blur_sigma_screen_px=1.0, irradiance_scale=2e5)
    truth = setup.truth()
    period, steps = 32.0, 8
    plan = _cosine_plan(period, steps)
    sensor = SensorModel(bit_depth=12, full_well_e=10000, read_noise_e=3.0)
    # Noise-free irradiance: the rendering's own bias.
    clean = np.stack(
        [
            setup.render_irradiance(np.broadcast_to(_line(period, k, steps), (360, 640)))
            for k in range(steps)
        ]
    )
    phase, _mod = _decode(clean.astype(np.float64), steps)
    inner = truth["visible"] & (truth["edge_distance_px"] > 4 * period)
    assert inner.mean() > 0.2
    bias = _wrap_px(phase, truth["x_true"], period)[inner]
    # Noisy frames through the sensor: error spread matches the docs/physics.md prediction.
    frames, ft = render_plan_frames(
        plan,
        setup,
        sensor,
        exposure_s=0.02,
        display_gamma=None,
        dither=None,
        bit_depth_display=10,
        rng=np.random.default_rng(5),
    )
    nphase, nmod = _decode(frames.astype(np.float64), steps)
    err = _wrap_px(nphase, truth["x_true"], period)[inner]
    # Shot noise varies with the pattern; the phase error sees the RMS over the steps.
    sigma_v = np.sqrt(np.mean(ft["noise_sigma_dn"].astype(np.float64) ** 2, axis=0))[inner]
    predicted = period / (2 * np.pi) * np.sqrt(2 / steps) * sigma_v / nmod[inner]
    assert np.abs(bias).max() < 0.1 * np.median(predicted)
    assert abs(np.mean(err)) < 0.1 * np.median(predicted)
    assert np.std(err / predicted) == pytest.approx(1.0, abs=0.06)


def _line(period: float, step: int, steps: int) -> np.ndarray:
    """One x-axis cosine row of the test screen in linear light."""
    c = np.arange(SCREEN.width_px)
    return 0.5 + 0.5 * np.cos(2 * np.pi * c / period + 2 * np.pi * step / steps)


@pytest.mark.parametrize("period", [16.0, 24.0, 48.0])
def test_blur_reduces_modulation_as_predicted(period: float) -> None:
    cam = mild_pinhole(W, H)
    pose = look_at_pose(SCREEN, distance_mm=600.0, tilt_deg=20)
    blur = 3.0
    mods = []
    for sigma in (0.0, blur):
        setup = OpticalSetup(cam, pose, SCREEN, blur_sigma_screen_px=sigma, vignetting=0.0)
        stack = np.stack(
            [
                setup.render_irradiance(np.broadcast_to(_line(period, k, 8), (360, 640)))
                for k in range(8)
            ]
        )
        mods.append(_decode(stack.astype(np.float64), 8)[1])
        inner = setup.truth()["visible"] & (setup.truth()["edge_distance_px"] > 6 * blur)
    ratio = np.median(mods[1][inner] / mods[0][inner])
    expected = np.exp(-2 * np.pi**2 * blur**2 / period**2)
    assert ratio == pytest.approx(expected, rel=0.03)


@pytest.mark.parametrize("distance_mm", [150.0, 450.0])
def test_truth_blur_width_predicts_modulation_of_the_whole_chain(distance_mm: float) -> None:
    cam = mild_pinhole(W, H)
    pose = look_at_pose(SCREEN, distance_mm=distance_mm, tilt_deg=25, tilt_azimuth_deg=30)
    setup = OpticalSetup(cam, pose, SCREEN, blur_sigma_screen_px=0.8, vignetting=0.0)
    truth = setup.truth()
    inner = truth["visible"] & (truth["edge_distance_px"] > 30) & np.isfinite(truth["blur_x"])
    flat = setup.render_irradiance(np.ones((360, 640)))
    for period in (12.0, 20.0, 40.0):
        stack = np.stack(
            [
                setup.render_irradiance(np.broadcast_to(_line(period, k, 8), (360, 640)))
                for k in range(8)
            ]
        )
        mod = _decode(stack.astype(np.float64), 8)[1][inner] / (0.5 * flat[inner])
        predicted = np.exp(-2 * np.pi**2 * truth["blur_x"][inner] ** 2 / period**2)
        ratio = mod / predicted
        assert np.median(ratio) == pytest.approx(1.0, abs=0.015)
        assert np.percentile(np.abs(ratio - 1), 90) < 0.04


@pytest.mark.parametrize("axis", ["x", "y"])
def test_separable_fast_path_equals_general_sampling(axis: str) -> None:
    cam = mild_pinhole(W, H)
    pose = look_at_pose(SCREEN, distance_mm=300.0, tilt_deg=15, roll_deg=10)
    setup = OpticalSetup(cam, pose, SCREEN, blur_sigma_screen_px=1.5, vignetting=0.1)
    truth = setup.truth()
    assert np.nanmin(np.hypot(truth["x_true"], truth["y_true"])) > 20  # screen corner unseen
    line = 0.5 + 0.5 * np.cos(2 * np.pi * np.arange(640 if axis == "x" else 360) / 21.0)
    img = np.broadcast_to(line if axis == "x" else line[:, None], (360, 640)).copy()
    fast = setup.render_irradiance(img)
    img[0, 0] += 1e-3  # not seen, not within blur reach: forces the general path
    general = setup.render_irradiance(img)
    np.testing.assert_allclose(fast, general, rtol=2e-6, atol=1e-6 * setup.irradiance_scale)
    assert fast.std() > 0.1 * fast.mean()


def test_vignetting_and_ambient() -> None:
    cam = mild_pinhole(W, H)
    setup = _frontal_setup(cam, vignetting=0.3, ambient=500.0, irradiance_scale=1e5)
    img = setup.render_irradiance(np.ones((360, 640)))
    assert setup.truth()["visible"].all()
    assert img[(H - 1) // 2 : (H + 2) // 2, (W - 1) // 2].mean() == pytest.approx(
        1e5 + 500, rel=1e-3
    )
    corners = img[[0, 0, -1, -1], [0, -1, 0, -1]]
    np.testing.assert_allclose(corners, 0.7 * 1e5 + 500, rtol=0.01)
    dark = setup.render_irradiance(np.zeros((360, 640)))
    np.testing.assert_allclose(dark, 500.0)
    with pytest.raises(ValueError, match="display image"):
        setup.render_irradiance(np.zeros((10, 10)))


def test_partially_visible_pixels_get_partial_light() -> None:
    cam = mild_pinhole(W, H)
    setup = OpticalSetup(cam, look_at_pose(SCREEN, distance_mm=1500.0), SCREEN, vignetting=0.0)
    img = setup.render_irradiance(np.ones((360, 640)))
    t = setup.truth()
    assert not t["visible"].all() and t["visible"].any()
    np.testing.assert_allclose(img[t["visible"]], setup.irradiance_scale, rtol=1e-5)
    assert np.all(img[~t["visible_center"] & ~t["visible"]] < setup.irradiance_scale)


# -- sensor --------------------------------------------------------------------------


@pytest.mark.parametrize("bits,dtype", [(8, np.uint8), (12, np.uint16), (16, np.uint16)])
def test_sensor_bit_depth_and_saturation(bits: int, dtype: type) -> None:
    sensor = SensorModel(bit_depth=bits, full_well_e=20000, read_noise_e=2.0, black_level_dn=3.0)
    rng = np.random.default_rng(0)
    irr = np.array([[0.0, 1e4, 1e9]])
    out = sensor.expose(irr, 0.5, 0.0, rng)
    assert out.dtype == dtype
    assert out[0, 2] == (1 << bits) - 1  # saturated stays at the top DN
    assert out[0, 1] == pytest.approx(sensor.mean_dn(irr, 0.5)[0, 1], rel=0.05)
    # Gain: +6.02 dB doubles the signal; the clipped pixel stays clipped.
    hi = sensor.expose(np.full((50, 50), 4e3), 0.5, 20 * np.log10(2), rng).astype(float)
    lo = sensor.expose(np.full((50, 50), 4e3), 0.5, 0.0, rng).astype(float)
    assert (hi.mean() - 3.0) / (lo.mean() - 3.0) == pytest.approx(2.0, rel=0.02)
    with pytest.raises(ValueError, match="bit_depth"):
        SensorModel(bit_depth=9)


@pytest.mark.parametrize("exact", [True, False])
def test_sensor_noise_matches_model(exact: bool) -> None:
    sensor = SensorModel(
        bit_depth=12, full_well_e=8000, read_noise_e=4.0, black_level_dn=20.0, exact_poisson=exact
    )
    rng = np.random.default_rng(3)
    for level, gain_db in ((50.0, 0.0), (3000.0, 0.0), (1000.0, 12.0)):
        irr = np.full((300, 300), level)
        frame = sensor.expose(irr, 1.0, gain_db, rng).astype(np.float64)
        mean = sensor.mean_dn(irr, 1.0, gain_db)
        sig = sensor.noise_sigma_dn(mean, gain_db)
        assert frame.mean() == pytest.approx(mean[0, 0], abs=0.05 * sig[0, 0] + 0.05)
        assert frame.std() == pytest.approx(sig[0, 0], rel=0.03)


# -- synthetic data ------------------------------------------------------------------


def test_synthetic_maps_noise_outliers_and_io(tmp_path) -> None:
    cam = wide_fisheye(W, H)
    pose = random_poses(cam, SCREEN, 1, np.random.default_rng(9))[0]
    maps, truth = synthetic_maps(
        cam,
        pose,
        SCREEN,
        sigma_px=0.1,
        rng=np.random.default_rng(1),
        outlier_fraction=0.02,
        valid_fraction=0.9,
        pose_id="p7",
    )
    maps.validate()
    assert maps.meta["pose_id"] == "p7"
    vis = truth["visible"]
    assert maps.mask.sum() == pytest.approx(0.9 * vis.sum(), rel=0.05)
    assert not (maps.mask & ~vis).any()
    good = maps.mask & ~truth["outliers"]
    err = (maps.x - truth["x_true"])[good]
    assert np.std(err) == pytest.approx(0.1, rel=0.05) and abs(err.mean()) < 0.01
    assert truth["outliers"].sum() == pytest.approx(0.02 * maps.mask.sum(), rel=0.3)
    assert np.isnan(maps.x[~maps.mask]).all()
    path = tmp_path / "m.npz"
    path.write_bytes(maps.to_npz_bytes())
    back = load_maps(path)
    np.testing.assert_array_equal(back.mask, maps.mask)


def test_render_plan_frames_with_gamma_and_lut() -> None:
    small = ScreenGeometry(320, 180, (1.6, 1.6))
    # 4 steps alias gamma's 3rd harmonic into the phase: the error the LUT must remove
    plan = build_plan(320, 180, 1.6, preset="fast", steps=4)
    cam = mild_pinhole(80, 60)
    setup = OpticalSetup(cam, look_at_pose(small, distance_mm=250.0), small, vignetting=0.2)
    sensor = SensorModel(bit_depth=12)
    kw = {"exposure_s": 0.02, "bit_depth_display": 8, "rng": np.random.default_rng(0)}
    frames, truth = render_plan_frames(plan, setup, sensor, display_gamma=2.2, **kw)
    assert frames.shape == (len(plan.frames), 60, 80) and frames.dtype == np.uint16
    assert truth["noise_sigma_dn"].shape == frames.shape
    assert truth["visible"].all() and not truth["saturated"].any()
    white, dark = plan.flat_indices(1.0)[0], plan.flat_indices(0.0)[0]
    assert frames[white].mean() > 10 * (frames[dark].mean() + 1)
    # Gamma distorts the cosine (harmonics); the matching LUT removes it at the source.
    finest = plan.period_sets("x")[-1]
    ok = truth["edge_distance_px"] > 2 * finest.period_px

    def phase_error(stack: np.ndarray) -> float:
        """RMS decoded-minus-true position (screen px) of the finest x period."""
        sub = stack[list(finest.frame_indices)].astype(np.float64)
        phase, _ = _decode(sub, finest.steps)
        return float(np.sqrt(np.mean(_wrap_px(phase, truth["x_true"], finest.period_px)[ok] ** 2)))

    lut = DisplayResponse.gamma(2.2)
    _, fixed = render_plan_frames(plan, setup, sensor, display_gamma=2.2, lut=lut, **kw)
    # Compared on the noise-free means: the systematic error is what the LUT removes.
    assert phase_error(fixed["mean_dn"]) < 0.3 * phase_error(truth["mean_dn"])
    with pytest.raises(ValueError, match="screen"):
        render_plan_frames(plan, _frontal_setup(cam), sensor, **kw)


def test_render_plan_frames_flags_saturation() -> None:
    small = ScreenGeometry(320, 180, (1.6, 1.6))
    plan = build_plan(320, 180, 1.6, preset="fast")
    setup = OpticalSetup(mild_pinhole(40, 30), look_at_pose(small, distance_mm=250.0), small)
    sensor = SensorModel(bit_depth=8, full_well_e=5000)
    frames, truth = render_plan_frames(
        plan, setup, sensor, exposure_s=0.2, rng=np.random.default_rng(0)
    )
    white = plan.flat_indices(1.0)[0]
    assert truth["saturated"].all() and (frames[white] == 255).all()
    _, ok = render_plan_frames(plan, setup, sensor, exposure_s=0.005, rng=np.random.default_rng(0))
    assert not ok["saturated"].any()


def test_changing_a_setup_field_resets_its_cache() -> None:
    setup = _frontal_setup(mild_pinhole(40, 30), vignetting=0.0)
    img = np.broadcast_to(_line(8.0, 0, 4), (360, 640))
    sharp = setup.render_irradiance(img)
    setup.blur_sigma_screen_px = 4.0
    soft = setup.render_irradiance(img)
    assert soft.std() < 0.5 * sharp.std()
    setup.pose = look_at_pose(SCREEN, distance_mm=5000.0)
    assert not setup.truth()["visible"].all()
