"""The one screen tracer (calibration/metrology/screen_trace.py) behind the parametric fits'
`ScreenModel` and sGCC's fitted screen: same numbers in both fits, and the values and
Jacobians of the parametric tracer it replaced."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from calibration.fit.sgcc.screen_terms import panel_ray_terms, rays_in_screen_frame
from calibration.metrology.screen import ScreenModel
from calibration.metrology.screen_trace import ScreenTrace
from calibration.shared.plan import ScreenGeometry

SCREEN = ScreenGeometry(1920, 1080, (0.2745, 0.2745))

# (params, index, origin, slope) -> panel point and dQ/do, dQ/dq, dQ/dparams of the parametric
# fits' pixel-major tracer as it stood before both fits shared one (17 significant digits).
REFERENCE = [
    ((0.5, 0.3, 0.2, 1.5), 1.52, (120.5, 80.25, -350.0), (0.31, -0.42),
     [228.89737988021437, -66.6109662893227],
     [[0.9996967068700661, -0.001147780346674649, -0.31038804687532384],
      [0.00041091327281377277, 1.0015550572438818, 0.42052574092785805]],
     [[349.5076602180925, -0.3264816344022414], [0.21854515394792887, 350.11129731181717]],
     [[-0.060093394349549537, 0.33536555115685857, 0.03602291383390896, -0.12034408460533647],
      [0.08141685686068002, -0.45436623059961484, -0.04880523809755408, 0.16304682430400425]]),
    ((-0.8, 0.45, -0.3, 3.0), 1.7, (410.0, 260.0, -180.0), (-0.65, 0.12),
     [293.7903202892146, 281.4540947158373],
     [[1.0005821504954413, -0.0017648575822657227, 0.6505901807319088],
      [-0.00010747393761992265, 1.0003258198613414, -0.12010895644281391]],
     [[178.50443992929334, -0.24468015104627272], [0.05163372972631586, 178.8292943521707]],
     [[0.10800897626106706, -0.1606919938507476, -0.035038602952671666, 0.31308162465515255],
      [-0.019940118694350844, 0.029666214249368782, 0.006468665160493231, -0.05779968455172046]]),
]


def _rays(rng: np.random.Generator, n: int) -> tuple[np.ndarray, np.ndarray]:
    """Pixel-major origins (n,3) in front of the panel and slopes (n,2) up to 50 degrees."""
    o = np.column_stack([rng.uniform(-50, 550, n), rng.uniform(-50, 350, n),
                         rng.uniform(-700, -60, n)])
    return o, rng.uniform(-0.85, 0.85, (n, 2))


@pytest.mark.parametrize("case", range(len(REFERENCE)))
def test_tracer_keeps_the_values_of_the_parametric_tracer(case: int) -> None:
    """Points and Jacobians equal the stored values to floating-point noise, both through
    `ScreenModel` (pixel-major) and `ScreenTrace` (feature-major)."""
    params, index, o, q, want_pts, want_o, want_q, want_s = REFERENCE[case]
    pts, jac = ScreenModel(SCREEN, "fit", index, np.array(params)).trace(
        np.array([o]), np.array([q]))
    for got, want in ((pts[0], want_pts), (jac["o"][0], want_o), (jac["q"][0], want_q),
                      (jac["s"][0], want_s)):
        np.testing.assert_allclose(got, want, rtol=1e-13, atol=1e-15)
    fm = ScreenTrace.of(SCREEN, index).trace(np, np.array(params), np.array(o)[:, None],
                                             np.array(q)[:, None])
    for got, want in zip(fm, (want_pts, want_o, want_q, want_s), strict=True):
        np.testing.assert_allclose(got[..., 0], want, rtol=1e-13, atol=1e-15)


def test_parametric_and_sgcc_fits_trace_bit_identically() -> None:
    """Both fits see the same panel to the last bit: ScreenModel's points and Jacobians are
    the shared tracer's, and sGCC's residuals (points only, and with Jacobians) put the ray
    where ScreenModel does."""
    rng = np.random.default_rng(5)
    params = np.array([0.7, -0.4, 0.25, 2.2])
    o, q = _rays(rng, 400)
    pts, jac = ScreenModel(SCREEN, "fit", 1.6, params).trace(o, q)
    fm = ScreenTrace.of(SCREEN, 1.6).trace(np, params, o.T.copy(), q.T.copy())
    for got, want in zip((pts, jac["o"], jac["q"], jac["s"]), fm, strict=True):
        np.testing.assert_array_equal(got, np.moveaxis(want, -1, 0))
    np.testing.assert_array_equal(ScreenModel(SCREEN, "fit", 1.6, params).trace(o, q, False)[0],
                                  pts)
    # sGCC: non-central spline components (direction log-map, origin) of one pose.
    n = 300
    comps = np.vstack([rng.uniform(-0.5, 0.5, (2, n)), rng.uniform(-20, 20, (2, n))])
    rc = Rotation.from_rotvec([0.1, -0.2, 0.05]).as_matrix()
    tc = np.array([260.0, 150.0, -320.0])
    screen = rng.uniform(0, 500, (2, n))
    panel = (ScreenTrace.of(SCREEN, 1.6), params)
    for jacobian in (False, True):  # (the direction maps differ in the last bits)
        _, r_s, o_s, ok, rz = rays_in_screen_frame(np, comps, rc, tc, jacobian)
        assert ok.all()
        want = ScreenModel(SCREEN, "fit", 1.6, params).trace(o_s.T, (r_s[:2] / rz).T)[0]
        res = panel_ray_terms(np, comps, rc, tc, screen, jacobian, panel)[0]
        np.testing.assert_array_equal(res, want.T - screen)


def test_origin_jacobian_equals_finite_differences() -> None:
    """dQ/do (the pose's share of the Jacobians) against central differences."""
    rng = np.random.default_rng(7)
    sm = ScreenModel(SCREEN, "fit", 1.52, np.array([0.5, 0.3, -0.2, 1.5]))
    o, q = _rays(rng, 40)
    jo = sm.trace(o, q)[1]["o"]
    for i in range(3):
        e = 1e-4 * np.eye(3)[i]
        fd = (sm.trace(o + e, q, False)[0] - sm.trace(o - e, q, False)[0]) / 2e-4
        np.testing.assert_allclose(fd, jo[:, :, i], rtol=1e-7, atol=1e-9)


def test_no_rays_give_empty_results() -> None:
    """An empty batch (a pose whose pixels all fell out) traces to empty arrays."""
    pts, jac = ScreenModel(SCREEN, "fit", 1.52, np.array([0.5, 0.3, 0.2, 1.5])).trace(
        np.empty((0, 3)), np.empty((0, 2)))
    assert pts.shape == (0, 2)
    assert {k: v.shape for k, v in jac.items()} == {"o": (0, 2, 3), "q": (0, 2, 2),
                                                    "s": (0, 2, 4)}
