"""Held-out views score the extrinsics: the target pose of a view left out of the fit is
found from one camera alone (the first that saw it, the reference camera when it did), and
the other cameras' data of that view are predicted through the fitted extrinsics. Their
residuals, whitened by the data's own sigma, should look like noise (RMS near 1) if the
extrinsics hold, as a single camera's held-out poses score its rays."""

from __future__ import annotations

from typing import Any

import cv2
import numpy as np

from calibration.fit.rig.blocks import Block
from calibration.fit.rig.problem import RigCameraState, RigProblem
from calibration.fit.rig.transforms import Transform, compose, invert
from calibration.models.base import CameraModel


def _frozen(model: CameraModel) -> RigCameraState:
    return RigCameraState(model, np.zeros(model.get_params().size, dtype=bool))


def pnp_start(block: Block, model: CameraModel) -> Transform:
    """A target-to-camera guess from one block: PnP on the model's ray directions (any model
    with rays; a non-central model's origins are small next to the target distance)."""
    _, d = model.unproject(block.pixels)
    ok = np.all(np.isfinite(d), axis=1) & (d[:, 2] > 0.1)
    if ok.sum() < 6:
        raise ValueError(f"{block.camera}/{block.view}: only {int(ok.sum())} usable points "
                         "for the held-out view's pose (need >= 6)")
    norm = d[ok, :2] / d[ok, 2:]
    good, rvec, tvec = cv2.solvePnP(block.target[ok], norm, np.eye(3), None,
                                    flags=cv2.SOLVEPNP_ITERATIVE)
    if not good:
        raise ValueError(f"{block.camera}/{block.view}: no pose found for the held-out view")
    return cv2.Rodrigues(rvec)[0], tvec.ravel()


def score_view(view: str, blocks: list[Block], models: dict[str, CameraModel],
               extrinsics: dict[str, Transform], order: list[str]) -> dict[str, Any]:
    """One held-out view: its anchor camera, and per other camera the RMS residual (px or mm
    on the target) and the whitened RMS."""
    cams = [c for c in order if any(b.camera == c for b in blocks)]
    if len(cams) < 2:
        return {"view": view, "anchor": cams[0] if cams else None, "cameras": {},
                "note": "seen by one camera only: nothing to score"}
    anchor = cams[0]
    anchor_blocks = [b for b in blocks if b.camera == anchor]
    problem = RigProblem({anchor: _frozen(models[anchor])}, anchor, [view], anchor_blocks)
    x0 = problem.pack({}, {view: pnp_start(anchor_blocks[0], models[anchor])})
    x, _ = problem.solve(x0)
    pose_ref = compose(invert(extrinsics[anchor]), problem.pose(x, view))
    out: dict[str, Any] = {"view": view, "anchor": anchor, "cameras": {}}
    for b in blocks:
        if b.camera == anchor:
            continue
        tf = compose(extrinsics[b.camera], pose_ref)
        w = b.residuals(models[b.camera], tf)
        raw = b.raw_residuals(models[b.camera], tf)
        ok = np.all(np.isfinite(w), axis=1)
        unit = "rms_mm" if b.kind == "ray" else "rms_px"
        out["cameras"][b.camera] = {
            unit: float(np.sqrt(np.mean(np.sum(raw[ok] ** 2, axis=1)))) if ok.any() else None,
            "whitened_rms": float(np.sqrt(np.mean(w[ok] ** 2))) if ok.any() else None,
            "n_points": int(ok.sum())}
    return out
