"""What a rig calibration reads: one camera's data of one view, as decoded maps or target
observations, named by camera and view."""

from __future__ import annotations

from dataclasses import dataclass

from calibration.shared.maps import DecodedMaps
from calibration.shared.observations import TargetObservations


@dataclass(frozen=True)
class RigInput:
    """Camera `camera` in view `view` (views shared by name were taken with the target in one
    pose); exactly one of `maps` and `observations` is set."""

    camera: str
    view: str
    maps: DecodedMaps | None = None
    observations: TargetObservations | None = None

    def __post_init__(self) -> None:
        """Exactly one kind of data, and names a file path can carry."""
        if (self.maps is None) == (self.observations is None):
            raise ValueError(f"{self.camera}/{self.view}: expected maps or observations (one)")
        for what, name in (("camera", self.camera), ("view", self.view)):
            if not name or "/" in name or "=" in name:
                raise ValueError(f"{what}: expected a non-empty name without '/' or '=', "
                                 f"got {name!r}")

    @property
    def image_size(self) -> tuple[int, int]:
        """(W, H) of the camera image."""
        if self.maps is not None:
            h, w = self.maps.shape
            return w, h
        assert self.observations is not None
        return self.observations.image_size
