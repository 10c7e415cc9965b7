"""Sturm–Ramalingam generic model: one ray per pixel, stored as a table on a pixel grid.

Table nodes sit at pixels (i * grid_step, j * grid_step). `unproject` interpolates
bilinearly (directions renormalized); it returns NaN where any of the four surrounding
nodes has no ray (pixels seen in < 2 poses) and beyond the last node. `project` runs a
vectorized Gauss-Newton on (u, v) seeded from the nearest table direction (KD-tree).
Tables are stored as base64 float32 (the in-memory model is rounded the same way, so a
saved and reloaded model is identical to the fitted one).
"""

from __future__ import annotations

import base64
from typing import Any

import numpy as np
from scipy.spatial import cKDTree

from calibration.models.base import CameraModel, ModelError, register_model

_PROJECT_ITERS = 50
_PROJECT_TOL_PX = 1e-10
_PROJECT_MAX_ANGLE = 1e-9
_SNAP_PX = 1e-9


def default_grid_step(image_size: tuple[int, int]) -> int:
    """Table step in pixels: 1 up to 640x480 (full resolution), 2 above (4x smaller JSON)."""
    return 1 if image_size[0] * image_size[1] <= 640 * 480 else 2


def encode_array(arr: np.ndarray) -> dict[str, Any]:
    """A float array as {"shape", "dtype": "float32", "data": base64 little-endian}."""
    a = np.ascontiguousarray(arr, dtype="<f4")
    return {"shape": list(a.shape), "dtype": "float32", "data": base64.b64encode(a).decode()}


def decode_array(obj: Any, name: str, shape: tuple[int, ...]) -> np.ndarray:
    """Inverse of `encode_array`, checked against the expected shape; float64 result."""
    if not isinstance(obj, dict) or obj.get("dtype") != "float32":
        raise ModelError(f"params.{name}: expected {{shape, dtype: 'float32', data: base64}}")
    if list(obj.get("shape", [])) != list(shape):
        raise ModelError(f"params.{name}: expected shape {list(shape)}, got {obj.get('shape')}")
    try:
        raw = base64.b64decode(obj["data"], validate=True)
    except (KeyError, ValueError) as exc:
        raise ModelError(f"params.{name}: data is not valid base64 ({exc})") from None
    if len(raw) != 4 * int(np.prod(shape)):
        raise ModelError(f"params.{name}: {len(raw)} bytes, expected {4 * int(np.prod(shape))}")
    return np.frombuffer(raw, dtype="<f4").reshape(shape).astype(np.float64)


def _f32(arr: np.ndarray) -> np.ndarray:
    """Round to float32 precision (what the JSON stores), kept as float64."""
    return np.asarray(arr, dtype=np.float32).astype(np.float64)


@register_model
class RayGridModel(CameraModel):
    """Per-pixel ray table (directions, and origins when non-central) with interpolation."""

    type_name = "raygrid"

    def __init__(
        self,
        image_size: tuple[int, int],
        grid_step: int,
        directions: np.ndarray,
        origins: np.ndarray | None = None,
        direction_std: np.ndarray | None = None,
        origin_std: np.ndarray | None = None,
    ) -> None:
        super().__init__(image_size)
        if int(grid_step) < 1:
            raise ModelError(f"grid_step: expected a positive integer, got {grid_step}")
        self.grid_step = int(grid_step)
        w, h = self.image_size
        self.table_shape = ((h - 1) // self.grid_step + 1, (w - 1) // self.grid_step + 1)
        shape3 = (*self.table_shape, 3)
        d = np.asarray(directions, dtype=np.float64)
        if d.shape != shape3:
            raise ModelError(f"directions: expected shape {list(shape3)}, got {list(d.shape)}")
        self.directions = _f32(d)
        self.central = origins is None
        if origins is not None and np.shape(origins) != shape3:
            got = list(np.shape(origins))
            raise ModelError(f"origins: expected shape {list(shape3)}, got {got}")
        self.origins = None if origins is None else _f32(origins)
        self.direction_std = None if direction_std is None else _f32(direction_std)
        self.origin_std = None if origin_std is None else _f32(origin_std)
        self._tree: tuple[cKDTree, np.ndarray] | None = None
        self._cells_ok: np.ndarray | None = None

    @property
    def is_central(self) -> bool:  # type: ignore[override]
        """Central when the table has no origins."""
        return self.central

    def covered(self) -> np.ndarray:
        """Boolean (H', W') mask of table nodes that have a ray."""
        return np.all(np.isfinite(self.directions), axis=2)

    def _cells(self, pixels: np.ndarray) -> tuple[np.ndarray, ...]:
        """Table cell (i0, j0), fractions (fu, fv) and inside-mask of pixels (N, 2).

        A pixel on a node line belongs to the cell after it unless only the cell before it
        has rays (so the coverage boundary itself is covered, from either side).
        """
        s = float(self.grid_step)
        hh, ww = self.table_shape
        gu, gv = pixels[:, 0] / s, pixels[:, 1] / s
        inside = (gu >= 0) & (gu <= ww - 1) & (gv >= 0) & (gv <= hh - 1)
        gu, gv = np.where(inside, gu, 0.0), np.where(inside, gv, 0.0)
        i0 = np.clip(np.floor(gu).astype(np.int64), 0, max(ww - 2, 0))
        j0 = np.clip(np.floor(gv).astype(np.int64), 0, max(hh - 2, 0))
        if hh > 1 and ww > 1:
            ok = self._cell_ok()
            back = ~ok[j0, i0] & (gu == i0) & (i0 > 0)
            back[back] = ok[j0[back], i0[back] - 1]
            i0 = i0 - back
            back = ~ok[j0, i0] & (gv == j0) & (j0 > 0)
            back[back] = ok[j0[back] - 1, i0[back]]
            j0 = j0 - back
        return i0, j0, (gu - i0)[:, None], (gv - j0)[:, None], inside

    def _cell_ok(self) -> np.ndarray:
        """(H'-1, W'-1) mask of table cells whose four corner nodes all have rays."""
        if self._cells_ok is None:
            c = self.covered()
            self._cells_ok = c[:-1, :-1] & c[:-1, 1:] & c[1:, :-1] & c[1:, 1:]
        return self._cells_ok

    def _interp(
        self, table: np.ndarray, pixels: np.ndarray, derivatives: bool = False
    ) -> tuple[np.ndarray, ...]:
        """Bilinear values (N, C) of a (H', W', C) table, optionally with d/du, d/dv."""
        hh, ww = self.table_shape
        i0, j0, fu, fv, inside = self._cells(pixels)
        i1, j1 = np.minimum(i0 + 1, ww - 1), np.minimum(j0 + 1, hh - 1)
        t00, t01 = table[j0, i0], table[j0, i1]
        t10, t11 = table[j1, i0], table[j1, i1]
        top, bot = t00 + fu * (t01 - t00), t10 + fu * (t11 - t10)
        val = top + fv * (bot - top)
        val[~inside] = np.nan
        if not derivatives:
            return (val,)
        s = float(self.grid_step)
        du = ((1 - fv) * (t01 - t00) + fv * (t11 - t10)) / s
        dv = (bot - top) / s
        return val, du, dv

    def unproject(self, pixels: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Pixels (N, 2) -> (origins, unit directions); NaN where the table has no ray."""
        pix = np.asarray(pixels, dtype=np.float64).reshape(-1, 2)
        (d,) = self._interp(self.directions, pix)
        d = d / np.linalg.norm(d, axis=1, keepdims=True)
        if self.origins is None:
            o = np.where(np.isfinite(d), 0.0, np.nan)
        else:
            (o,) = self._interp(self.origins, pix)
        return o, d

    def ray_std(self, pixels: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Interpolated 1-sigma direction (rad) and origin (mm) uncertainty of pixels (N, 2)."""
        pix = np.asarray(pixels, dtype=np.float64).reshape(-1, 2)
        if self.direction_std is None:
            raise ModelError("direction_std: this raygrid model carries no uncertainty table")
        (ang,) = self._interp(self.direction_std[..., None], pix)
        if self.origin_std is None:
            return ang[:, 0], np.where(np.isfinite(ang[:, 0]), 0.0, np.nan)
        (org,) = self._interp(self.origin_std[..., None], pix)
        return ang[:, 0], org[:, 0]

    def rays_with_derivatives(self, pix: np.ndarray) -> tuple[np.ndarray, ...]:
        """Origins, unit directions and their d/du, d/dv at pixels (N, 2)."""
        n, ndu, ndv = self._interp(self.directions, pix, derivatives=True)
        norm = np.linalg.norm(n, axis=1, keepdims=True)
        d = n / norm
        ddu = (ndu - np.sum(ndu * d, axis=1, keepdims=True) * d) / norm
        ddv = (ndv - np.sum(ndv * d, axis=1, keepdims=True) * d) / norm
        if self.origins is None:
            zero = np.zeros_like(d)
            return zero, zero, zero, d, ddu, ddv
        o, odu, odv = self._interp(self.origins, pix, derivatives=True)
        return o, odu, odv, d, ddu, ddv

    def _seed_tree(self) -> tuple[cKDTree, np.ndarray]:
        """KD-tree over the covered table directions and their node pixels."""
        if self._tree is None:
            ok = self.covered()
            jj, ii = np.nonzero(ok)
            nodes = np.stack([ii, jj], axis=1).astype(np.float64) * self.grid_step
            self._tree = (cKDTree(self.directions[ok]), nodes)
        return self._tree

    def project(self, points: np.ndarray) -> np.ndarray:
        """3D points (N, 3) mm -> pixels (N, 2) by Gauss-Newton on (u, v); NaN if not seen."""
        p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        out = np.full((len(p), 2), np.nan)
        tree, nodes = self._seed_tree()
        if len(nodes) == 0 or len(p) == 0:
            return out
        o_mean = np.zeros(3) if self.origins is None else np.nanmean(self.origins, axis=(0, 1))
        q = p - o_mean
        qn = q / np.linalg.norm(q, axis=1, keepdims=True)
        good = np.all(np.isfinite(qn), axis=1)
        # Query only real directions: the zero vector is equidistant from every unit vector,
        # which defeats the tree's pruning.
        idx = np.zeros(len(p), dtype=np.int64)
        idx[good] = tree.query(qn[good])[1]
        hi = np.array([(self.table_shape[1] - 1), (self.table_shape[0] - 1)]) * self.grid_step
        uv = self._seed(nodes[idx], p, hi)
        prev, last = uv.copy(), np.zeros_like(uv)
        active = good.copy()
        for _ in range(_PROJECT_ITERS):
            if not active.any():
                break
            sel = np.flatnonzero(active)
            res, jac = self._project_residual(uv[sel], p[sel])
            ok = np.all(np.isfinite(res), axis=1) & np.all(np.isfinite(jac), axis=(1, 2))
            ok[ok] = np.abs(np.linalg.det(jac[ok])) > 1e-300
            # A step into a cell without rays is halved (backtracking from the last good point).
            back = sel[~ok]
            last[back] *= 0.5
            uv[back] = self._snap(prev[back] + last[back])
            active[back[np.max(np.abs(last[back]), axis=1) < _PROJECT_TOL_PX]] = False
            fwd = sel[ok]
            step = -np.linalg.solve(jac[ok], res[ok][..., None])[..., 0]
            prev[fwd] = uv[fwd]
            uv[fwd] = self._snap(np.clip(uv[fwd] + step, 0.0, hi))
            last[fwd] = uv[fwd] - prev[fwd]
            active[fwd[np.max(np.abs(step), axis=1) < _PROJECT_TOL_PX]] = False
        res, _ = self._project_residual(uv, p)
        o, d = self.unproject(uv)
        ahead = np.sum((p - o) * d, axis=1) > 0
        fine = good & ahead & (np.linalg.norm(res, axis=1) < _PROJECT_MAX_ANGLE)
        out[fine] = uv[fine]
        return out

    def _snap(self, uv: np.ndarray) -> np.ndarray:
        """Move coordinates within 1e-9 px of a node line onto it (coverage edges are lines)."""
        s = float(self.grid_step)
        node = np.round(uv / s) * s
        return np.where(np.abs(uv - node) < _SNAP_PX, node, uv)

    def _seed(self, nodes: np.ndarray, p: np.ndarray, hi: np.ndarray) -> np.ndarray:
        """Best start among a node and the centers of its 4 cells (a node may border no ray)."""
        half = 0.5 * self.grid_step
        offsets = np.array([[0.0, 0.0], [-half, -half], [half, -half], [-half, half], [half, half]])
        cand = np.clip(nodes[None] + offsets[:, None], 0.0, hi)  # (5, N, 2)
        res, _ = self._project_residual(cand.reshape(-1, 2), np.tile(p, (5, 1)))
        err = np.linalg.norm(res, axis=1).reshape(5, -1)
        best = np.argmin(np.where(np.isfinite(err), err, np.inf), axis=0)
        return cand[best, np.arange(len(p))]

    def _project_residual(self, uv: np.ndarray, p: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Residual (N,2): ray direction minus unit(P - origin), in a basis normal to it."""
        o, odu, odv, d, ddu, ddv = self.rays_with_derivatives(uv)
        w = p - o
        wn = np.linalg.norm(w, axis=1, keepdims=True)
        wh = w / wn
        e1 = np.cross(wh, np.where(np.abs(wh[:, :1]) < 0.9, [[1.0, 0, 0]], [[0, 1.0, 0]]))
        e1 /= np.linalg.norm(e1, axis=1, keepdims=True)
        e2 = np.cross(wh, e1)
        basis = np.stack([e1, e2], axis=1)  # (N, 2, 3)
        res = np.einsum("nij,nj->ni", basis, d - wh)
        cols = []
        for dd, do in ((ddu, odu), (ddv, odv)):
            dwh = (-do + np.sum(do * wh, axis=1, keepdims=True) * wh) / wn
            cols.append(np.einsum("nij,nj->ni", basis, dd - dwh))
        return res, np.stack(cols, axis=2)

    def get_params(self) -> np.ndarray:
        """Directions (and origins) table flattened."""
        parts = [self.directions.ravel()]
        if self.origins is not None:
            parts.append(self.origins.ravel())
        return np.concatenate(parts)

    def set_params(self, vector: np.ndarray) -> None:
        """Set the tables from a `get_params()` vector."""
        v = np.asarray(vector, dtype=np.float64).ravel()
        n = self.directions.size
        expected = n * (1 if self.origins is None else 2)
        if v.size != expected:
            raise ModelError(f"params: expected {expected} values, got {v.size}")
        self.directions = _f32(v[:n].reshape(self.directions.shape))
        if self.origins is not None:
            self.origins = _f32(v[n:].reshape(self.origins.shape))
        self._tree, self._cells_ok = None, None

    def params_to_json(self) -> dict[str, Any]:
        """{central, grid_step, directions, origins?, direction_std?, origin_std?}."""
        out: dict[str, Any] = {
            "central": self.central,
            "grid_step": self.grid_step,
            "directions": encode_array(self.directions),
        }
        for key in ("origins", "direction_std", "origin_std"):
            arr = getattr(self, key)
            if arr is not None:
                out[key] = encode_array(arr)
        return out

    @classmethod
    def from_params_json(cls, image_size: tuple[int, int], params: dict[str, Any]) -> RayGridModel:
        """Rebuild from `params_to_json()` output."""
        step = params.get("grid_step")
        if not isinstance(step, int) or isinstance(step, bool) or step < 1:
            raise ModelError(f"params.grid_step: expected a positive integer, got {step!r}")
        central = params.get("central")
        if not isinstance(central, bool):
            raise ModelError(f"params.central: expected true/false, got {central!r}")
        w, h = int(image_size[0]), int(image_size[1])
        shape = ((h - 1) // step + 1, (w - 1) // step + 1)
        d = decode_array(params.get("directions"), "directions", (*shape, 3))
        o = None if central else decode_array(params.get("origins"), "origins", (*shape, 3))
        ds = params.get("direction_std")
        os_ = params.get("origin_std")
        return cls(
            (w, h),
            step,
            d,
            o,
            None if ds is None else decode_array(ds, "direction_std", shape),
            None if os_ is None or central else decode_array(os_, "origin_std", shape),
        )
