"""A varied starting set of screen poses, planned from the camera's nominal lens (a pinhole,
or an equidistant fisheye for a wide-angle lens) and the screen alone (before any pose is
captured).

The set is chosen greedily among the candidate placements
(`calibration.guidance_placement`) at 0.7/1/1.4 times the distance where the screen spans
half the image width: the first two for information volume (each raises the log
determinant of the parameters' information most), each later
one for the smallest worst predicted ray sigma of the set so far, as next-pose chooses
(the information is the nominal lens's own parameters', poses marginalized). So
the set mixes tilt directions and positions across the image, and never repeats a
placement.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from calibration.guidance_placement import (
    CENTRE_FRACTIONS,
    TILTS,
    Placement,
    candidate_placements,
    outline_distance,
    planned_points,
)
from calibration.models.parametric import FisheyeModel, OpenCV5Model, PinholeFamily
from calibration.shared.plan import ScreenGeometry
from calibration.uncertainty import (
    RAY_SIGMA_GRID,
    covariance,
    direction_jacobian,
    pose_information,
    ray_sigma,
    sensor_grid,
    worst_ray_sigma,
)

DEFAULT_HFOV_DEG = 60.0  # the nominal lens when nothing better is known
SPAN_OF_IMAGE = 0.5  # the reference distance: the screen spans this part of the image width
_DISTANCE_FACTORS = (0.7, 1.0, 1.4)
_SAMPLE_GRID = (24, 18)
_DISTINCT_FRACTION = 0.08  # outlines of two starting poses differ by this much at least
_D_OPTIMAL_PICKS = 2  # picked for information volume; later ones for the worst ray sigma


@dataclass
class NominalCamera:
    """The distortion-free camera the starting set is planned with, and what was assumed."""

    model: PinholeFamily
    assumed: str

    def to_json(self) -> dict[str, object]:
        """`image_size`, `camera_matrix`, `projection` and `assumed` (words)."""
        return {"image_size": list(self.model.image_size),
                "camera_matrix": self.model.camera_matrix.tolist(),
                "projection": self.model.type_name, "assumed": self.assumed}


def nominal_camera(image_size: tuple[int, int], camera_matrix: np.ndarray | None = None,
                   hfov_deg: float | None = None, source: str = "",
                   fisheye: bool = False) -> NominalCamera:
    """A distortion-free camera: `camera_matrix` (measured, e.g. quick intrinsics; `source`
    says where from) or else a horizontal field of view (default `DEFAULT_HFOV_DEG`) with
    square pixels and the principal point at the image centre; a pinhole, or with `fisheye`
    an equidistant fisheye (r = f theta), whose field of view may pass 180 degrees' half."""
    w, h = image_size
    kind = FisheyeModel if fisheye else OpenCV5Model
    lens = "an equidistant fisheye" if fisheye else "a pinhole"
    if camera_matrix is not None:
        k = np.asarray(camera_matrix, np.float64)
        return NominalCamera(kind(image_size, k),
                             f"{lens} with the measured camera matrix ({source}: fx "
                             f"{k[0, 0]:.1f} px, fy {k[1, 1]:.1f} px), no distortion")
    fov = DEFAULT_HFOV_DEG if hfov_deg is None else float(hfov_deg)
    top = 200.0 if fisheye else 150.0
    if not 5.0 <= fov <= top:
        raise ValueError(f"hfov_deg: expected a horizontal field of view in [5, {top:.0f}] "
                         f"deg for {lens}, got {fov}")
    half = np.radians(fov) / 2
    f = (w / 2) / (half if fisheye else np.tan(half))
    k = np.array([[f, 0, (w - 1) / 2], [0, f, (h - 1) / 2], [0, 0, 1.0]])
    said = "given" if hfov_deg is not None else "assumed (no intrinsics measured yet)"
    return NominalCamera(kind(image_size, k),
                         f"{lens} with {fov:.0f} deg horizontal field of view {said}: fx = "
                         f"fy = {f:.1f} px, principal point at the image centre, no "
                         "distortion")


def reference_distance(camera: NominalCamera, screen: ScreenGeometry) -> float:
    """Distance (mm) at which the screen, facing the camera, spans `SPAN_OF_IMAGE` of the
    image width."""
    width_mm = (screen.width_px - 1) * screen.pitch_mm[0]
    return float(camera.model.fx * width_mm / (SPAN_OF_IMAGE * camera.model.image_size[0]))


def starting_poses(camera: NominalCamera, screen: ScreenGeometry, count: int) -> list[Placement]:
    """`count` varied placements, most informative first (see the module docstring)."""
    if not 1 <= count <= 12:
        raise ValueError(f"count: expected 1..12 starting poses, got {count}")
    model = camera.model
    cands = [p for p, _, _ in candidate_placements(
        model, screen, reference_distance(camera, screen), _DISTANCE_FACTORS,
        CENTRE_FRACTIONS[::2], TILTS)]
    if not cands:
        raise ValueError("starting poses: no placement shows the whole screen in this camera's "
                         "view; check the screen size and the camera's field of view")
    samples = sensor_grid(model.image_size, *_SAMPLE_GRID)
    rays = model.unproject(samples)
    free = np.arange(model.get_params().size)
    infos = [_information(model, screen, p, rays, samples, free) for p in cands]
    scale = np.outer(*2 * [np.sqrt(np.clip(np.mean([np.diag(i) for i in infos], axis=0),
                                           1e-300, None))])
    prior = 1e-6 * np.diag(np.diag(scale))  # keeps the first picks' information invertible
    grid = sensor_grid(model.image_size, *RAY_SIGMA_GRID)
    jd = direction_jacobian(model, grid, free)
    total = np.zeros((len(free), len(free)))
    chosen: list[Placement] = []
    while len(chosen) < count:
        best, best_score = None, np.inf
        for p, info in zip(cands, infos, strict=True):
            if any(outline_distance(p.outline_px, c.outline_px, model.image_size)
                   < _DISTINCT_FRACTION for c in chosen):
                continue
            both = total + info
            score = (-np.linalg.slogdet(both / scale + 1e-6 * np.eye(len(free)))[1]
                     if len(chosen) < _D_OPTIMAL_PICKS else
                     worst_ray_sigma(model, grid, ray_sigma(jd, covariance(both + prior))))
            if score < best_score:
                best, best_score = (p, info), score
        if best is None:
            break
        chosen.append(best[0])
        total = total + best[1]
    return chosen


def _information(model: PinholeFamily, screen: ScreenGeometry, placement: Placement,
                 rays: tuple[np.ndarray, np.ndarray], samples: np.ndarray,
                 free: np.ndarray) -> np.ndarray:
    """Information a placement adds on the model's parameters, per sampled pixel it shows."""
    pts = planned_points(rays, samples, screen, placement.rotation,
                                   placement.translation, np.array([0.05, 0.05]))
    return pose_information(model, placement.rotation, placement.translation, pts, free)
