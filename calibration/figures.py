"""Matplotlib figures that threads of one process may draw: each is its own `Figure` (never
pyplot's global figure registry), and every drawing function runs under one process-wide
lock (`one_at_a_time`): matplotlib's text layout is not thread-safe (two guidance plots drawn
at once failed in mathtext's shared parser on their log-scale tick labels)."""

from __future__ import annotations

import functools
import threading
from collections.abc import Callable
from typing import Any, ParamSpec, TypeVar

from matplotlib.figure import Figure

_DRAWING = threading.RLock()
P = ParamSpec("P")
R = TypeVar("R")


def one_at_a_time(draw: Callable[P, R]) -> Callable[P, R]:
    """Run `draw` (a function that builds and saves figures) under the drawing lock."""
    @functools.wraps(draw)
    def locked(*args: P.args, **kwargs: P.kwargs) -> R:
        with _DRAWING:
            return draw(*args, **kwargs)
    return locked


def subplots(ncols: int, figsize: tuple[float, float]) -> tuple[Figure, Any]:
    """A figure of `ncols` axes in a row, not registered with pyplot."""
    fig = Figure(figsize=figsize)
    axes = fig.subplots(1, ncols)
    return fig, axes
