"""The model registry: each model name with its model class, fit function, typed options and
minimum pose count. The CLI, the worker tasks and the REST API (model enum, per-model
options schema, 422 at the request) all read it, so a model is listed exactly once.

Fit functions and model classes are named by import path and loaded on first use, so
reading the registry (e.g. to build a request schema) does not import the numerics.
"""

from __future__ import annotations

import importlib
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from pydantic import BaseModel, ValidationError

from calibration.fit.classic.options import MIN_POSES as CLASSIC_MIN_POSES
from calibration.fit.classic.options import ParametricOptions
from calibration.fit.raygrid.options import MIN_POSES as RAYGRID_MIN_POSES
from calibration.fit.raygrid.options import RaygridOptions
from calibration.fit.sgcc.options import MIN_POSES as SGCC_MIN_POSES
from calibration.fit.sgcc.options import SgccOptions


def _load(path: str) -> Any:
    """The object named "package.module:attribute"."""
    module, _, attr = path.partition(":")
    return getattr(importlib.import_module(module), attr)


@dataclass(frozen=True)
class ModelSpec:
    """One calibratable model: what it is, how it is fitted, which options it takes."""

    name: str
    family: str  # "classic", "raygrid" or "sgcc"
    model_path: str  # "module:Class" of the CameraModel
    fit_path: str  # "module:function" with the signature of `dispatch.calibrate`
    options: type[BaseModel]
    min_poses: int  # training poses the fit needs

    @property
    def model_class(self) -> type:
        """The `CameraModel` subclass this fit produces."""
        return _load(self.model_path)

    @property
    def fit(self) -> Callable[..., Any]:
        """fit(maps, screen, name, *, options, heldout, progress, cancelled) -> result."""
        return _load(self.fit_path)

    def parse_options(self, options: dict[str, Any] | BaseModel | None) -> Any:
        """Typed options (given ones pass through); ValueError naming the first bad field
        (`options.<field>: why, got <value>`)."""
        if isinstance(options, self.options):
            return options
        try:
            return self.options.model_validate(options or {})
        except ValidationError as exc:
            err = exc.errors()[0]
            if err["type"] == "extra_forbidden":
                unknown = sorted(set(options or {}) - set(self.options.model_fields))
                raise ValueError(f"options: unknown key(s) {unknown} for {self.name}; known: "
                                 f"{sorted(self.options.model_fields)}") from None
            where = ".".join(str(p) for p in ("options", *err["loc"][:1]))
            why = str(err["ctx"]["error"]) if err["type"] == "value_error" else err["msg"]
            raise ValueError(f"{where}: {why}, got {err['input']!r} (model {self.name})") from None


_CLASSIC_FIT = "calibration.fit.classic.calibrate:calibrate_parametric"
_PARAMETRIC = "calibration.models.parametric"
MODELS: dict[str, ModelSpec] = {s.name: s for s in (
    ModelSpec("opencv5", "classic", f"{_PARAMETRIC}:OpenCV5Model", _CLASSIC_FIT,
              ParametricOptions, CLASSIC_MIN_POSES),
    ModelSpec("opencv-rational", "classic", f"{_PARAMETRIC}:OpenCVRationalModel", _CLASSIC_FIT,
              ParametricOptions, CLASSIC_MIN_POSES),
    ModelSpec("fisheye", "classic", f"{_PARAMETRIC}:FisheyeModel", _CLASSIC_FIT,
              ParametricOptions, CLASSIC_MIN_POSES),
    ModelSpec("raygrid", "raygrid", "calibration.models.raygrid:RayGridModel",
              "calibration.fit.raygrid.calibrate:calibrate_raygrid", RaygridOptions,
              RAYGRID_MIN_POSES),
    ModelSpec("sgcc", "sgcc", "calibration.models.sgcc:SGCCModel",
              "calibration.fit.sgcc.calibrate:calibrate_generic", SgccOptions, SGCC_MIN_POSES),
    ModelSpec("sgcc-noncentral", "sgcc", "calibration.models.sgcc:SGCCNonCentralModel",
              "calibration.fit.sgcc.calibrate:calibrate_generic", SgccOptions, SGCC_MIN_POSES),
)}
MODEL_NAMES = tuple(MODELS)
PARAMETRIC = tuple(n for n, s in MODELS.items() if s.family == "classic")


def model_spec(name: str) -> ModelSpec:
    """The registry entry of `name`; ValueError listing the known models otherwise."""
    if name not in MODELS:
        raise ValueError(f"model: expected one of {list(MODEL_NAMES)}, got {name!r}")
    return MODELS[name]
