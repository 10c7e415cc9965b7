"""An independent renderer for decoder honesty checks (no hw_mocks camera or sensor code).

A flat monitor (device codes through its own gamma and black level, each screen pixel a
uniform square) seen by an equidistant fisheye (r = f theta) or a pinhole camera; every
camera pixel integrates its area by s x s sub-samples; the sensor adds Poisson shot noise
on electrons, Gaussian read noise, a black level, vignetting, and quantizes with clipping.
The truth of a pixel is the light-weighted mean screen coordinate of its sub-samples.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from acquisition.patterns import frame_linear
from calibration.shared.plan import CosineFrame, Plan


@dataclass(frozen=True)
class Camera:
    """Equidistant fisheye (`fov_deg` across the image width) or pinhole (`fov_deg` likewise)."""

    width: int
    height: int
    fov_deg: float = 150.0
    kind: str = "fisheye"  # or "pinhole"
    stride: int = 1  # image pixel (i, j) is sensor pixel (i, j) * stride of a larger sensor
    pupil_shift_mm: float = 0.0  # non-central: a ray at field angle theta starts at z = s theta^2

    def directions(self, sub: int) -> np.ndarray:
        """(H, W, sub*sub, 3) unit ray directions of each pixel's sub-samples (camera frame).

        With `stride` > 1 the image holds every stride-th pixel of a sensor `stride` times
        larger (the same field of view): a high-resolution camera's footprints at a small
        image's cost."""
        half = math.radians(self.fov_deg) / 2.0
        off = (np.arange(sub) + 0.5) / sub - 0.5
        k = self.stride
        u = (np.arange(self.width) * k + k // 2)[None, :, None, None] + off[None, None, None, :]
        v = (np.arange(self.height) * k + k // 2)[:, None, None, None] + off[None, None, :, None]
        u, v = np.broadcast_arrays(u, v)
        x = u - (self.width * k - 1) / 2.0
        y = v - (self.height * k - 1) / 2.0
        shape = (self.height, self.width, sub * sub)
        x, y = x.reshape(shape), y.reshape(shape)
        if self.kind == "fisheye":
            f = (self.width * k / 2.0) / half
            r = np.hypot(x, y)
            theta = r / f
            s = np.where(r > 0, np.sin(theta) / np.maximum(r, 1e-12), 1.0 / f)
            d = np.stack([x * s, y * s, np.cos(theta)], axis=-1)
            d[theta >= math.pi / 2] = np.nan  # behind the camera
            return d
        f = (self.width * k / 2.0) / math.tan(half)
        d = np.stack([x / f, y / f, np.ones_like(x)], axis=-1)
        return d / np.linalg.norm(d, axis=-1, keepdims=True)


@dataclass(frozen=True)
class Sensor:
    """Linear sensor: electrons -> DN; 8-bit by default."""

    gain_e_per_dn: float = 20.0
    read_dn: float = 0.5
    black_dn: float = 4.0
    full_well_e: float = 1e9
    bits: int = 8

    def expose(self, electrons: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        e = rng.poisson(np.minimum(electrons, self.full_well_e)).astype(np.float64)
        dn = e / self.gain_e_per_dn + self.black_dn + rng.normal(0.0, self.read_dn, e.shape)
        top = (1 << self.bits) - 1
        out = np.clip(np.rint(dn), 0, top)
        return out.astype(np.uint8 if self.bits == 8 else np.uint16)


@dataclass(frozen=True)
class Monitor:
    """Emitted light (0..1 of peak) of device code c: black + (1 - black) (c/255)^gamma."""

    gamma: float = 2.2
    black: float = 0.002
    lut: bool = True  # the patterns are pre-compensated for the gamma (a measured LUT)
    bits: int = 8

    def light(self, linear: np.ndarray) -> np.ndarray:
        top = (1 << self.bits) - 1
        target = np.clip(linear, 0.0, 1.0)
        code = np.rint((target ** (1.0 / self.gamma) if self.lut else target) * top)
        return self.black + (1.0 - self.black) * (code / top) ** self.gamma


@dataclass(frozen=True)
class Scene:
    """Camera looking at the screen centre from `distance_mm`, the screen tilted."""

    camera: Camera
    sensor: Sensor = field(default_factory=Sensor)
    monitor: Monitor = field(default_factory=Monitor)
    distance_mm: float = 150.0
    tilt_deg: float = 20.0
    pitch_mm: float = 0.2745
    peak_e: float = 3000.0  # electrons of a full-white screen pixel at the image centre
    vignetting: float = 0.0  # relative irradiance falls as cos(theta)^(4 * vignetting)
    sub: int = 4
    pixelated: bool = False  # screen pixels as uniform squares (else a continuous pattern)


def screen_hits(scene: Scene, plan: Plan) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Screen coordinates (px, pixel i centred at i) of every sub-sample, NaN off the screen,
    and the per-sample cos(theta) (for vignetting)."""
    d = scene.camera.directions(scene.sub)
    t = math.radians(scene.tilt_deg)
    # screen frame: origin at its centre, axes ex, ey in-plane, normal n facing the camera
    ex = np.array([math.cos(t), 0.0, math.sin(t)])
    ey = np.array([0.0, 1.0, 0.0])
    n = np.cross(ex, ey)
    centre = np.array([0.0, 0.0, scene.distance_mm])
    origin = np.zeros(d.shape)
    origin[..., 2] = scene.camera.pupil_shift_mm * np.arccos(np.clip(d[..., 2], -1.0, 1.0)) ** 2
    with np.errstate(invalid="ignore", divide="ignore"):
        lam = ((centre - origin) @ n) / (d @ n)
        p = origin + d * lam[..., None] - centre
    sx = (p @ ex) / scene.pitch_mm + (plan.screen.width_px - 1) / 2.0
    sy = (p @ ey) / scene.pitch_mm + (plan.screen.height_px - 1) / 2.0
    inside = (lam > 0) & (sx >= -0.5) & (sx < plan.screen.width_px - 0.5)
    inside &= (sy >= -0.5) & (sy < plan.screen.height_px - 0.5)
    sx, sy = np.where(inside, sx, np.nan), np.where(inside, sy, np.nan)
    return sx, sy, d[..., 2]


def render(scene: Scene, plan: Plan, seed: int = 0) -> tuple[np.ndarray, dict[str, np.ndarray]]:
    """(F, H, W) frames of the plan and the truth: x_true, y_true, visible (every sub-sample
    on the screen)."""
    rng = np.random.default_rng(seed)
    sx, sy, cos_t = screen_hits(scene, plan)
    on = np.isfinite(sx)
    ix = np.where(on, np.rint(sx), 0).astype(np.int64)
    iy = np.where(on, np.rint(sy), 0).astype(np.int64)
    weight = scene.peak_e / scene.sub**2 * np.where(on, 1.0, 0.0)
    if scene.vignetting:
        weight = weight * np.clip(np.nan_to_num(cos_t), 0.0, 1.0) ** (4 * scene.vignetting)
    frames = []
    for i, fr in enumerate(plan.frames):
        if isinstance(fr, CosineFrame) and scene.pixelated:
            line = frame_linear(plan, i)[0] if fr.axis == "x" else frame_linear(plan, i)[:, 0]
            light = scene.monitor.light(line)[ix if fr.axis == "x" else iy]
        elif isinstance(fr, CosineFrame):
            c = np.nan_to_num(sx if fr.axis == "x" else sy)
            phase = 2.0 * np.pi * c / fr.period_px + fr.phase_shift
            light = scene.monitor.light(fr.offset + fr.amplitude * np.cos(phase))
        else:
            light = scene.monitor.light(np.array([fr.level]))[0] * np.ones(ix.shape)
        electrons = (light * weight).sum(axis=-1)
        frames.append(scene.sensor.expose(electrons, rng))
    total = weight.sum(axis=-1)
    with np.errstate(invalid="ignore", divide="ignore"):
        truth = {  # the light-weighted centroid of the pixel's footprint
            "x_true": (np.nan_to_num(sx) * weight).sum(axis=-1) / total,
            "y_true": (np.nan_to_num(sy) * weight).sum(axis=-1) / total,
            "visible": on.sum(axis=-1) == scene.sub**2,
        }
    return np.stack(frames), truth


def normalized_errors(maps, truth: dict[str, np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """(z, radius fraction) over valid pixels, both axes: z = (decoded - truth) / sigma."""
    zs, rs = [], []
    h, w = maps.mask.shape
    yy, xx = np.mgrid[0:h, 0:w]
    radius = np.hypot(xx - (w - 1) / 2, yy - (h - 1) / 2) / (w / 2)
    for ax in ("x", "y"):
        err = (getattr(maps, ax) - truth[f"{ax}_true"])[maps.mask]
        zs.append(err / getattr(maps, f"sigma_{ax}")[maps.mask])
        rs.append(radius[maps.mask])
    return np.concatenate(zs), np.concatenate(rs)
