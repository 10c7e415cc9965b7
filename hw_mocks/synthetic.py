"""Ground-truth test data: exact decoded maps with noise, and static renderings of plan frames."""

from __future__ import annotations

from typing import Any

import numpy as np

from acquisition.patterns import DisplayResponse, render_frame
from calibration.shared.maps import MAPS_FORMAT, DecodedMaps
from calibration.shared.plan import Plan, ScreenGeometry
from hw_mocks.cameras import TruthCamera
from hw_mocks.optics import OpticalSetup
from hw_mocks.panel import PanelShape
from hw_mocks.scene import ScreenPose, screen_points
from hw_mocks.sensor import SensorModel

# Observed modulation written into synthetic maps (camera units; only its constancy matters).
_SYNTHETIC_MODULATION = 100.0


def synthetic_maps(
    camera: TruthCamera,
    pose: ScreenPose,
    screen: ScreenGeometry,
    *,
    sigma_px: float = 0.05,
    rng: np.random.Generator,
    outlier_fraction: float = 0.0,
    valid_fraction: float = 1.0,
    pose_id: str = "",
    panel: PanelShape | None = None,
) -> tuple[DecodedMaps, dict[str, Any]]:
    """Exact screen points of each pixel plus Gaussian noise of `sigma_px`, as DecodedMaps.

    `valid_fraction` keeps a random subset of the visible pixels in the mask;
    `outlier_fraction` of the kept pixels get a uniformly random screen point instead
    (gross decoding errors that slipped through; marked in truth["outliers"]).
    `panel` bends and refracts the rays (a shaped panel behind cover glass; default ideal).
    """
    if sigma_px < 0:
        raise ValueError(f"sigma_px: expected >= 0, got {sigma_px}")
    for name, value in (("outlier_fraction", outlier_fraction), ("valid_fraction", valid_fraction)):
        if not 0.0 <= value <= 1.0:
            raise ValueError(f"{name}: expected in [0, 1], got {value}")
    x_true, y_true = screen_points(camera, pose, screen, panel=panel)
    visible = np.isfinite(x_true)
    mask = visible & (rng.random(visible.shape) < valid_fraction)
    x = x_true + sigma_px * rng.standard_normal(x_true.shape)
    y = y_true + sigma_px * rng.standard_normal(y_true.shape)
    outliers = mask & (rng.random(mask.shape) < outlier_fraction)
    n_out = int(outliers.sum())
    x[outliers] = rng.uniform(-0.5, screen.width_px - 0.5, n_out)
    y[outliers] = rng.uniform(-0.5, screen.height_px - 0.5, n_out)
    x[~mask] = np.nan
    y[~mask] = np.nan
    sigma = np.where(mask, sigma_px, np.nan).astype(np.float32)
    modulation = np.where(mask, _SYNTHETIC_MODULATION, 0.0).astype(np.float32)
    maps = DecodedMaps(
        x=x,
        y=y,
        sigma_x=sigma,
        sigma_y=sigma.copy(),
        mask=mask,
        modulation_x=modulation,
        modulation_y=modulation.copy(),
        meta={
            "format": MAPS_FORMAT,
            "pose_id": pose_id,
            "camera": type(camera).__name__,
            "source": "hw_mocks.synthetic",
        },
    )
    truth = {
        "x_true": x_true,
        "y_true": y_true,
        "visible": visible,
        "outliers": outliers,
        "pose": pose,
        "camera": camera,
        "panel": panel or PanelShape(),
    }
    return maps, truth


def render_plan_frames(
    plan: Plan,
    setup: OpticalSetup,
    sensor: SensorModel,
    *,
    exposure_s: float,
    gain_db: float = 0.0,
    display_gamma: float | None = None,
    lut: DisplayResponse | None = None,
    bit_depth_display: int = 8,
    dither: str | None = "ordered",
    rng: np.random.Generator,
) -> tuple[np.ndarray, dict[str, Any]]:
    """Every plan frame through display, optics and sensor (no timing): (F,H,W) stack + truth.

    The display turns codes (from `render_frame`, pre-compensated by `lut` if given)
    into linear light as (code/top)**display_gamma (None: a linear display). truth adds
    to `setup.truth()` the noise-free mean DN and the sensor's noise sigma per frame
    (float32 (F,H,W)) and `saturated`, pixels whose mean comes within 3 sigma of the
    full well or the top DN in some frame (their samples may be clipped).
    """
    plan_size = (plan.screen.width_px, plan.screen.height_px)
    if plan_size != (setup.screen.width_px, setup.screen.height_px):
        raise ValueError(
            f"plan screen {plan.screen.width_px}x{plan.screen.height_px} differs from the "
            f"optical setup's screen {setup.screen.width_px}x{setup.screen.height_px}"
        )
    if display_gamma is not None and display_gamma <= 0:
        raise ValueError(f"display_gamma: expected > 0, got {display_gamma}")
    top = float((1 << bit_depth_display) - 1)
    h, w = setup.camera.height, setup.camera.width
    n = len(plan.frames)
    frames = np.empty((n, h, w), dtype=sensor.dtype)
    means = np.empty((n, h, w), dtype=np.float32)
    sigmas = np.empty((n, h, w), dtype=np.float32)
    saturated = np.zeros((h, w), dtype=bool)
    clip_dn = min(float(sensor.mean_dn(np.array(sensor.full_well_e), 1.0, gain_db)), sensor.max_dn)
    for i in range(n):
        codes = render_frame(
            plan, i, bit_depth=bit_depth_display, response=lut, dither=dither, rng=rng
        )
        linear = codes.astype(np.float32) / np.float32(top)
        if display_gamma is not None:
            linear = linear**display_gamma
        irradiance = setup.render_irradiance(linear)
        mean = sensor.mean_dn(irradiance, exposure_s, gain_db)
        frames[i] = sensor.expose(irradiance, exposure_s, gain_db, rng)
        means[i] = mean
        sigmas[i] = sensor.noise_sigma_dn(mean, gain_db)
        saturated |= mean + 3.0 * sigmas[i] >= clip_dn
    truth = setup.truth()
    truth.update(
        {
            "mean_dn": means,
            "noise_sigma_dn": sigmas,
            "saturated": saturated,
            "gain_db": gain_db,
            "exposure_s": exposure_s,
        }
    )
    return frames, truth
