"""Full-screen SDL window (pygame) on a chosen monitor: exact pixels, vsync'd flips.

The window covers the monitor at its native resolution with no scaling (no
`pygame.SCALED`), and grey codes are written unchanged into all three channels (no
colour management). With vsync the flip blocks until the vertical blank and its return
time is the flip time; where the driver cannot sync (dummy, offscreen, Xvfb) flips are
paced on the configured refresh period. pygame has no refresh-rate query, so the rate
comes from the rig config (default 60 Hz).
"""

from __future__ import annotations

import os

import numpy as np

from acquisition.clock import Clock, RealClock
from acquisition.display.vsync import VsyncPacer
from acquisition.errors import DisplayError
from acquisition.protocols import DisplayInfo

os.environ.setdefault("PYGAME_HIDE_SUPPORT_PROMPT", "1")


def list_monitors() -> list[tuple[int, int, int, str]]:
    """(index, width, height, video driver) of each monitor SDL sees; [] without a driver.

    The 'offscreen' and 'dummy' drivers report a virtual monitor: no real screen.
    """
    import pygame

    if pygame.display.get_init():  # a window is open in this process: do not close it
        return _monitors(pygame)
    try:
        pygame.display.init()
    except pygame.error:
        return []
    try:
        return _monitors(pygame)
    finally:
        pygame.display.quit()


def _monitors(pygame) -> list[tuple[int, int, int, str]]:
    driver = pygame.display.get_driver()
    return [(i, w, h, driver) for i, (w, h) in enumerate(pygame.display.get_desktop_sizes())]


class SdlDisplay:
    """A `Display` that is a borderless full-screen pygame window on monitor `monitor`."""

    def __init__(
        self,
        monitor: int = 0,
        *,
        size: tuple[int, int] | None = None,
        refresh_hz: float = 60.0,
        vsync: bool = True,
        clock: Clock | None = None,
        video_driver: str | None = None,
    ) -> None:
        import pygame

        self._pg = pygame
        self._clock = clock if clock is not None else RealClock()
        if video_driver:
            os.environ["SDL_VIDEODRIVER"] = video_driver
        # The window must land on the monitor's pixels 1:1: no DPI scaling by SDL.
        os.environ.setdefault("SDL_VIDEO_HIGHDPI_DISABLED", "1")
        try:
            pygame.display.init()
        except pygame.error as exc:
            raise DisplayError(
                f"SDL display: no video driver ({exc}); set SDL_VIDEODRIVER or DISPLAY"
            ) from exc
        try:
            sizes = pygame.display.get_desktop_sizes()
            if not 0 <= monitor < len(sizes):
                raise DisplayError(
                    f"SDL display: monitor {monitor} does not exist (found {len(sizes)}: "
                    f"{sizes})"
                )
            w, h = size if size is not None else sizes[monitor]
            # Full screen at the native size; a smaller area is a borderless window at the
            # monitor's top-left corner (SDL would otherwise change the video mode).
            flags = pygame.NOFRAME
            if (w, h) == tuple(sizes[monitor]):
                flags |= pygame.FULLSCREEN
            else:
                os.environ["SDL_VIDEO_WINDOW_POS"] = "0,0"
            self._surface, self.vsync_granted = self._open(w, h, flags, monitor, vsync)
            if self._surface.get_size() != (w, h):
                raise DisplayError(
                    f"SDL display: got a {self._surface.get_size()} window, asked {(w, h)} "
                    "(the driver scaled it; choose the monitor's native size)"
                )
            pygame.mouse.set_visible(False)
        except BaseException:
            pygame.display.quit()
            raise
        self._width, self._height = w, h
        self._pacer = VsyncPacer(self._clock, 1.0 / refresh_hz, None)
        if self.vsync_granted:
            self.vsync_granted = self._flips_are_synced(refresh_hz)
        driver = pygame.display.get_driver()
        self._info = DisplayInfo(f"sdl monitor {monitor} ({driver})", w, h, refresh_hz, 8)
        self._closed = False

    def _open(self, w: int, h: int, flags: int, monitor: int, vsync: bool):
        pg = self._pg
        if vsync:
            try:
                return pg.display.set_mode((w, h), flags, display=monitor, vsync=1), True
            except pg.error:
                pass  # this renderer cannot vsync: pace on the refresh period instead
        return pg.display.set_mode((w, h), flags, display=monitor), False

    def _flips_are_synced(self, refresh_hz: float, flips: int = 6) -> bool:
        """Whether flips really block on the vertical blank (some renderers accept vsync
        and ignore it): the median interval of a few black flips must be near a period."""
        self._surface.fill((0, 0, 0))
        times = []
        for _ in range(flips):
            self._pg.display.flip()
            times.append(self._clock.now())
        return float(np.median(np.diff(times))) > 0.5 / refresh_hz

    @property
    def info(self) -> DisplayInfo:
        return self._info

    def show(self, image: np.ndarray) -> float:
        """Draw the grey codes 1:1, flip, and return the flip time."""
        if self._closed:
            raise DisplayError("SDL display: show() after close()")
        img = np.asarray(image)
        if img.shape != (self._height, self._width):
            raise DisplayError(
                f"SDL display: image shape {img.shape} != screen ({self._height}, {self._width})"
            )
        if img.dtype != np.uint8:
            raise DisplayError(f"SDL display: expected uint8 codes (8-bit), got {img.dtype}")
        self._pg.event.pump()  # keep the window responsive (and the compositor happy)
        rgb = np.repeat(img.T[:, :, None], 3, axis=2)
        self._pg.surfarray.blit_array(self._surface, rgb)
        if self.vsync_granted:
            self._pg.display.flip()  # blocks until the vertical blank
            return self._clock.now()
        t = self._pacer.next_flip()
        self._pg.display.flip()
        return t

    def close(self) -> None:
        if self._closed:
            return
        self._closed = True
        self._pg.display.quit()
