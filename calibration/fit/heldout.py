"""Split a generic fit's poses into training and held-out sets, with one-line input errors."""

from __future__ import annotations

from collections.abc import Sequence

from calibration.shared.maps import DecodedMaps

MIN_TRAINING_POSES = 3


def split_heldout(
    maps: Sequence[DecodedMaps], heldout: Sequence[int] | None, model: str
) -> tuple[list[DecodedMaps], list[DecodedMaps], list[int]]:
    """(training maps, held-out maps, sorted held-out indices); ValueError on bad input."""
    held = sorted(set(heldout or []))
    if any(not 0 <= i < len(maps) for i in held):
        raise ValueError(f"heldout: expected pose indices in [0, {len(maps) - 1}], got {held}")
    held_maps = [maps[i] for i in held]
    train = [m for i, m in enumerate(maps) if i not in held]
    if len(train) < MIN_TRAINING_POSES:
        raise ValueError(f"maps: {model} calibration needs >= {MIN_TRAINING_POSES} poses, "
                         f"got {len(train)}")
    shapes = {m.shape for m in (*train, *held_maps)}
    if len(shapes) != 1:
        raise ValueError(f"maps: all poses must have the same image size, got {sorted(shapes)}")
    return train, held_maps, held
