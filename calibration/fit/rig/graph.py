"""Which cameras are tied together through shared views, and the order in which a start
value for each camera's pose is chained from the reference camera."""

from __future__ import annotations

from collections import deque
from collections.abc import Iterable


def views_by_camera(pairs: Iterable[tuple[str, str]]) -> dict[str, set[str]]:
    """camera -> the views it took part in, from (camera, view) pairs."""
    out: dict[str, set[str]] = {}
    for camera, view in pairs:
        out.setdefault(camera, set()).add(view)
    return out


def camera_groups(views: dict[str, set[str]]) -> list[list[str]]:
    """The connected groups of cameras (two cameras are tied when they share a view, and
    ties are transitive), each sorted, largest group first."""
    seen: set[str] = set()
    groups = []
    for start in sorted(views):
        if start in seen:
            continue
        group, queue = [], deque([start])
        seen.add(start)
        while queue:
            cam = queue.popleft()
            group.append(cam)
            for other in sorted(views):
                if other not in seen and views[cam] & views[other]:
                    seen.add(other)
                    queue.append(other)
        groups.append(sorted(group))
    return sorted(groups, key=lambda g: (-len(g), g))


def check_connected(views: dict[str, set[str]]) -> None:
    """ValueError naming the groups when the cameras are not all tied through shared views."""
    groups = camera_groups(views)
    if len(groups) > 1:
        listing = " | ".join(", ".join(g) for g in groups)
        raise ValueError(f"cameras: not connected through shared views; groups: {listing} "
                         "(add views that two groups see together)")


def chain_order(views: dict[str, set[str]], reference: str) -> list[tuple[str, str, list[str]]]:
    """Breadth-first (camera, parent, shared views) from the reference camera: each camera's
    pose is chained from a parent already placed, over the views they share (most first)."""
    placed, order = {reference}, []
    queue = deque([reference])
    while queue:
        parent = queue.popleft()
        for cam in sorted(views, key=lambda c: (-len(views[c] & views[parent]), c)):
            shared = sorted(views[cam] & views[parent])
            if cam not in placed and shared:
                placed.add(cam)
                order.append((cam, parent, shared))
                queue.append(cam)
    return order
