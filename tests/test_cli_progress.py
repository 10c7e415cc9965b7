"""CLI progress bars: drawn on a terminal, silent otherwise."""

from __future__ import annotations

import io

from api.progress import progress_bar


class _Terminal(io.StringIO):
    def isatty(self) -> bool:
        return True


def test_bar_is_drawn_on_a_terminal() -> None:
    out = _Terminal()
    with progress_bar("decode", out) as update:
        for i in range(3):
            update(i + 1, 3, "frames")
    text = out.getvalue()
    assert "decode: frames" in text and "3/3" in text


def test_bar_is_silent_when_not_a_terminal() -> None:
    out = io.StringIO()
    with progress_bar("calibrate", out) as update:
        update(1, 2, "fit")
        update(2, 2, "fit")
    assert out.getvalue() == ""
