"""The one camera-model interface every model implements, the registry, and model JSON I/O.

A model maps between camera pixels (u, v; docs/formats.md conventions) and rays in its own
camera frame (x right, y down, z forward, mm). Central models have all origins at 0.
"""

from __future__ import annotations

import json
import math
from abc import ABC, abstractmethod
from pathlib import Path
from typing import Any, ClassVar

import numpy as np

from calibration.shared.atomic import write_text_atomic

MODEL_FORMAT = "phasecal.model/1"


class ModelError(ValueError):
    """A model file or parameter set is malformed (message names the field)."""


class CameraModel(ABC):
    """Base class: subclasses set `type_name`, implement the abstract methods and register."""

    type_name: ClassVar[str]
    is_central: ClassVar[bool] = True

    def __init__(self, image_size: tuple[int, int]) -> None:
        w, h = (int(image_size[0]), int(image_size[1]))
        if w <= 0 or h <= 0:
            raise ModelError(f"image_size: expected positive [W, H], got {list(image_size)}")
        self.image_size: tuple[int, int] = (w, h)
        self.stats: dict[str, Any] = {}

    @abstractmethod
    def project(self, points: np.ndarray) -> np.ndarray:
        """3D points (N, 3) in the camera frame, mm -> pixels (N, 2); NaN rows if not seen."""

    @abstractmethod
    def unproject(self, pixels: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Pixels (N, 2) -> (origins (N, 3) mm, unit directions (N, 3)); NaN if undefined."""

    @abstractmethod
    def get_params(self) -> np.ndarray:
        """The model's free parameters as a flat float64 vector."""

    @abstractmethod
    def set_params(self, vector: np.ndarray) -> None:
        """Set the free parameters from a flat vector of `get_params()` layout."""

    @abstractmethod
    def params_to_json(self) -> dict[str, Any]:
        """The model's own parameters as JSON-serializable data (`params` of the file)."""

    @classmethod
    @abstractmethod
    def from_params_json(cls, image_size: tuple[int, int], params: dict[str, Any]) -> CameraModel:
        """Rebuild a model from `params_to_json()` output; raise `ModelError` if malformed."""

    def to_dict(self) -> dict[str, Any]:
        """The whole `phasecal.model/1` document."""
        return {
            "format": MODEL_FORMAT,
            "type": self.type_name,
            "image_size": list(self.image_size),
            "params": self.params_to_json(),
            "stats": jsonable(self.stats),
        }


_REGISTRY: dict[str, type[CameraModel]] = {}


def register_model(cls: type[CameraModel]) -> type[CameraModel]:
    """Class decorator: make a model type loadable by name."""
    _REGISTRY[cls.type_name] = cls
    return cls


def model_types() -> list[str]:
    """Names of all registered model types."""
    _import_builtin_models()
    return sorted(_REGISTRY)


def _import_builtin_models() -> None:
    """Import the model modules so they register (kept lazy to avoid import cycles)."""
    import importlib

    for mod in ("parametric", "raygrid", "sgcc"):
        try:
            importlib.import_module(f"calibration.models.{mod}")
        except ModuleNotFoundError as exc:
            if exc.name != f"calibration.models.{mod}":
                raise


def model_from_dict(data: Any, source: str = "model") -> CameraModel:
    """Validate a `phasecal.model/1` document and build the model."""
    if not isinstance(data, dict):
        raise ModelError(f"{source}: expected a JSON object, got {type(data).__name__}")
    if data.get("format") != MODEL_FORMAT:
        raise ModelError(f"{source}: format: expected {MODEL_FORMAT!r}, got {data.get('format')!r}")
    _import_builtin_models()
    mtype = data.get("type")
    if mtype not in _REGISTRY:
        raise ModelError(f"{source}: type: unknown model {mtype!r}; known: {model_types()}")
    size = data.get("image_size")
    if (
        not isinstance(size, list)
        or len(size) != 2
        or not all(isinstance(s, int) and not isinstance(s, bool) and s > 0 for s in size)
    ):
        raise ModelError(f"{source}: image_size: expected [W, H] positive integers, got {size!r}")
    params = data.get("params")
    if not isinstance(params, dict):
        raise ModelError(f"{source}: params: expected an object")
    try:
        model = _REGISTRY[mtype].from_params_json((size[0], size[1]), params)
    except ModelError as exc:
        raise ModelError(f"{source}: {exc}") from None
    except (KeyError, TypeError, ValueError) as exc:
        raise ModelError(f"{source}: params: malformed for model {mtype!r} ({exc})") from None
    stats = data.get("stats", {})
    model.stats = stats if isinstance(stats, dict) else {}
    return model


def load_model(path: str | Path) -> CameraModel:
    """Read a model JSON file."""
    p = Path(path)
    try:
        data = json.loads(p.read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise ModelError(f"{p}: model file not found") from None
    except json.JSONDecodeError as exc:
        raise ModelError(f"{p}: not valid JSON (line {exc.lineno}: {exc.msg})") from None
    return model_from_dict(data, source=str(p))


def save_model(model: CameraModel, path: str | Path) -> None:
    """Write a model JSON file atomically."""
    write_text_atomic(path, json.dumps(model.to_dict(), indent=1) + "\n")


def jsonable(value: Any) -> Any:
    """Fit statistics as plain JSON data: NumPy scalars and arrays become numbers and lists,
    dict keys strings, and NaN/infinities null (strict JSON has none), so model and result
    files parse in any JSON reader."""
    if isinstance(value, dict):
        return {str(k): jsonable(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [jsonable(v) for v in value]
    if isinstance(value, np.ndarray):
        return jsonable(value.tolist())
    if isinstance(value, np.generic):
        return jsonable(value.item())
    if isinstance(value, float) and not math.isfinite(value):
        return None
    return value
