"""Simulated rigs shared by the rig tests: cameras at known relative poses (hw_mocks truth)
and the fits of them, each fitted once per test session."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest

from calibration.fit.rig.calibrate import calibrate_rig
from calibration.fit.rig.inputs import RigInput
from calibration.fit.rig.result import RigResult
from calibration.fit.rig.transforms import to_rvec
from calibration.fit.sgcc.initial import gauge_rotation
from calibration.shared.maps import save_maps
from calibration.shared.observations import save_observations
from calibration.shared.plan import ScreenGeometry
from calibration.shared.rig_model import RigModel
from hw_mocks.camera_base import TruthCamera
from hw_mocks.cameras import mild_pinhole
from hw_mocks.rig_truth import (
    RigTruth,
    camera_at,
    grid_points,
    shared_views,
    view_maps,
    view_observations,
)

SCREEN = ScreenGeometry(640, 400, (0.5, 0.5))


@dataclass
class SimulatedRigFit:
    truth: RigTruth
    inputs: list[RigInput]
    result: RigResult


def two_pinholes() -> RigTruth:
    """Two 320x240 pinholes 150 mm apart, toed in by 6 degrees."""
    ra, ta = camera_at((0.0, 0.0, 0.0))
    rb, tb = camera_at((150.0, 0.0, 0.0), yaw_deg=-6.0)
    return RigTruth({"A": mild_pinhole(320, 240), "B": mild_pinhole(320, 240)},
                    {"A": ra, "B": rb}, {"A": ta, "B": tb})


def gauge_frame(cam: TruthCamera) -> np.ndarray:
    """Rotation from the truth camera's frame to the sGCC gauge's (the ray at the sensor
    centre +z, the row through it in the x-z plane), from the truth's own rays."""
    cu, cv = (cam.width - 1) / 2, (cam.height - 1) / 2
    _, d = cam.rays(np.array([cu, cu + 1e-3]), np.array([cv, cv]))
    return gauge_rotation(d[0], (d[1] - d[0]) / 1e-3)


def extrinsics_z(rig: RigModel, truth: RigTruth, frames: dict[str, np.ndarray]) -> np.ndarray:
    """B's pose relative to A against the truth (each camera in its model's frame), over the
    predicted 1-sigma: rotation vector, translation."""
    r_rel, t_rel = truth.relative("A", "B")
    r_true = frames["B"] @ r_rel @ frames["A"].T
    rot, t = rig.relative("A", "B")
    err = np.concatenate([to_rvec(rot @ r_true.T), t - frames["B"] @ t_rel])
    return err / np.sqrt(np.diag(rig.camera("B").covariance))


def board_view_files(folder: Path, truth: RigTruth, screen: ScreenGeometry, views: int,
                     rng: np.random.Generator, grid: tuple[int, int] = (11, 8)) -> list[str]:
    """`CAMERA/VIEW=PATH` arguments of `phasecal calibrate --observations`: A and B see
    `views` shared views of a board's `grid` of corners on `screen` (0.1 px noise), one
    observations file per camera and view, named `v0`, `v1`, ..."""
    board = grid_points(screen, *grid)
    inputs = []
    for k, (group, view) in enumerate(shared_views(truth, screen, [("A", "B")], views, rng)):
        for cam in group:
            path = folder / f"{cam}{k}.npz"
            save_observations(view_observations(truth, cam, view, board, sigma_px=0.1,
                                                rng=rng), path)
            inputs.append(f"{cam}/v{k}={path}")
    return inputs


def maps_view_files(folder: Path, truth: RigTruth, screen: ScreenGeometry, views: int,
                    rng: np.random.Generator) -> list[str]:
    """`CAMERA/VIEW=PATH` arguments of `phasecal calibrate --maps`: A and B see `views`
    shared views of `screen` (decoded maps, 0.05 px noise), one maps file per camera and
    view, named `v0`, `v1`, ... in view order."""
    for k, (group, view) in enumerate(shared_views(truth, screen, [("A", "B")], views, rng)):
        for cam in group:
            save_maps(view_maps(truth, cam, view, screen, sigma_px=0.05, rng=rng),
                      folder / f"{cam}{k}.npz")
    return [f"{c}/v{k}={folder / f'{c}{k}.npz'}" for k in range(views) for c in "AB"]


@pytest.fixture(scope="session")
def stereo_maps_fit() -> SimulatedRigFit:
    """Two cameras, 7 shared views of decoded maps (the last one held out), fitted as opencv5."""
    rng = np.random.default_rng(5)
    truth = two_pinholes()
    inputs = []
    for k, (group, view) in enumerate(shared_views(truth, SCREEN, [("A", "B")], 7, rng)):
        inputs += [RigInput(c, f"v{k}", maps=view_maps(truth, c, view, SCREEN, sigma_px=0.05,
                                                       rng=rng)) for c in group]
    result = calibrate_rig(inputs, "opencv5", SCREEN, options={"max_points_per_view": 600},
                           heldout_views=["v6"])
    return SimulatedRigFit(truth, inputs, result)
