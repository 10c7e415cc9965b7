"""The simulator's ground truth, for checks made from outside the product (simulator check).

The service never reads it. A check rebuilds a simulated rig's truth from the same
`phasecal.rig/1` config the service was given (the simulation is deterministic in its
config) and the screen poses the client asked for, then compares what the service
returned (decoded maps, unprojected rays) with it: `phasecal demo` prints the result as
its "simulator check", and tests call the same helpers.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np

from acquisition.rig import parse_rig_config
from calibration.shared.maps import DecodedMaps
from calibration.shared.plan import ScreenGeometry
from hw_mocks.arm import HandEyeRig
from hw_mocks.cameras import TruthCamera
from hw_mocks.poses import random_poses
from hw_mocks.rig import SimulatedRig, open_simulated_rig
from hw_mocks.scene import ScreenPose


def screen_pose_dict(pose: ScreenPose) -> dict[str, list[float]]:
    """A screen pose as the REST API's `screen_pose` (Rodrigues `rvec`, `tvec_mm`)."""
    rvec, _ = cv2.Rodrigues(np.asarray(pose.rotation, np.float64))
    return {"rvec": rvec.ravel().tolist(), "tvec_mm": np.asarray(pose.translation, float).tolist()}


def perfect_maps(sim: SimulatedRig) -> DecodedMaps:
    """What a perfect decode of the reference camera's current view gives (true screen px
    per pixel, zero sigma): checks of code that only reads where the screen is seen."""
    truth = sim.truth()
    mask = np.isfinite(truth["x_true"]) & np.isfinite(truth["y_true"])
    zero = np.zeros(mask.shape, np.float32)
    return DecodedMaps(truth["x_true"], truth["y_true"], zero, zero, mask, zero, zero)


@dataclass
class SimulatorTruth:
    """Ground truth of a simulated rig built from its config (the service's rig is its twin)."""

    sim: SimulatedRig
    start: ScreenPose  # where the screen is before any screen_pose moved it
    config: dict[str, Any]

    @classmethod
    def from_config(cls, config: dict[str, Any]) -> SimulatorTruth:
        """The truth of the simulated rig the service builds from `config`."""
        sim = SimulatedRig.from_config(config)
        return cls(sim, sim.pose, config)

    def handeye(self) -> HandEyeRig:
        """The true hand-eye and world-target transforms of the config's simulated mover
        (what a closed loop's hand-eye result is compared with)."""
        rig = open_simulated_rig(parse_rig_config(self.config, "simulator truth"))
        rig.close()
        if rig.simulated is None or not isinstance(rig.simulated, SimulatedRig) \
                or rig.simulated.handeye is None:
            raise ValueError("the rig config has no simulated mover")
        return rig.simulated.handeye

    @property
    def camera(self) -> TruthCamera:
        """The simulated camera's true model."""
        return self.sim.truth_camera

    @property
    def camera_names(self) -> list[str]:
        """The rig's cameras by name, the reference first."""
        return list(self.sim.cameras)

    def camera_of(self, name: str) -> TruthCamera:
        """One camera's true model (several-camera rigs)."""
        return self.sim.truth_camera_of(name)

    def extrinsics(self, name: str) -> tuple[np.ndarray, np.ndarray]:
        """(R, t_mm) of a camera: X_cam = R @ X_ref + t, the reference camera's frame mapped
        into that camera's (identity and zeros for the reference)."""
        mount = self.sim.mounts[name]
        return mount.rotation.copy(), mount.translation_mm.copy()

    @property
    def screen(self) -> ScreenGeometry:
        """The simulated screen."""
        return self.sim.screen

    def screen_poses(self, n: int, seed: int) -> list[dict[str, list[float]]]:
        """`n` varied screen poses that keep the screen in the simulated camera's view, as the
        REST API's `screen_pose` (what a person placing the screen would do by eye)."""
        poses = random_poses(self.camera, self.screen, n, np.random.default_rng(seed))
        return [screen_pose_dict(p) for p in poses]

    def screen_points(self, screen_pose: dict[str, Any] | None = None,
                      camera: str | None = None) -> tuple[np.ndarray, np.ndarray]:
        """True screen px (x, y) seen by each pixel centre of `camera` (default: the
        reference; NaN: none) with the screen at `screen_pose` (REST form, in the reference
        camera's frame; None: the rig's starting pose)."""
        if screen_pose is None:
            rot, tvec = self.start.rotation, self.start.translation
        else:
            rot, _ = cv2.Rodrigues(np.asarray(screen_pose["rvec"], np.float64))
            tvec = np.asarray(screen_pose["tvec_mm"], np.float64)
        self.sim.set_pose(rot, tvec)
        truth = self.sim.truth(camera)
        return truth["x_true"], truth["y_true"]

    def normalized_errors(self, maps: DecodedMaps, screen_pose: dict[str, Any] | None = None,
                          camera: str | None = None) -> np.ndarray:
        """(decoded - true) / decoded sigma over the valid pixels of `camera`'s maps, x then
        y: N(0, 1) iff the decoder's sigmas are honest."""
        x_true, y_true = self.screen_points(screen_pose, camera)
        return np.concatenate([((maps.x - x_true) / maps.sigma_x)[maps.mask],
                               ((maps.y - y_true) / maps.sigma_y)[maps.mask]])

    def ray_errors_mrad(self, pixels: np.ndarray, directions: np.ndarray) -> np.ndarray:
        """Angles (mrad) between fitted ray directions (N, 3) at `pixels` (N, 2) and the true
        ones, after the best rotation (a generic model's camera frame is defined only up to
        one, its gauge); rows without a fitted or true ray are left out."""
        _, d_true = self.camera.rays(pixels[:, 0], pixels[:, 1])
        ok = np.isfinite(directions).all(axis=1) & np.isfinite(d_true).all(axis=1)
        a, b = directions[ok], d_true[ok]
        u, _, vt = np.linalg.svd(a.T @ b)
        rot = u @ np.diag([1.0, 1.0, np.sign(np.linalg.det(u @ vt))]) @ vt
        cosang = np.clip(np.sum((a @ rot) * b, axis=1), -1.0, 1.0)
        return np.arccos(cosang) * 1e3
