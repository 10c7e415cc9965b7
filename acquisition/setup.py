"""Setup helpers: display->camera latency, exposure choice, display response (gamma) curve.

All of them only show flats and grab frames through the `Display`/`Camera` protocols,
so they work on simulated and real rigs alike (`phasecal check` reuses them).
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass, replace
from typing import Any

import numpy as np

from acquisition.clock import Clock
from acquisition.errors import AcquisitionError, FrameLost
from acquisition.patterns import DisplayResponse
from acquisition.protocols import Camera, CameraSettings, Display, Frame
from acquisition.rig import Rig


@dataclass(frozen=True)
class LatencyResult:
    """Measured flip-to-panel latency (whole refresh periods) and the evidence."""

    latency_s: float
    periods: int
    observations: int
    violations: int  # observations inconsistent with the chosen latency (0 when clean)
    undecided: tuple[int, ...] = ()  # other latencies (periods) the frames fit about as well


@dataclass(frozen=True)
class ExposureResult:
    """Chosen settings and the white flat's level at the target percentile."""

    settings: CameraSettings
    level_dn: float
    fraction_of_max: float
    iterations: int


#: Frames a link may lose in one `grab_after` before it gives up: each lost one is triggered
#: again, and more than this means the link, not a packet, is the problem.
MAX_LOST_FRAMES = 3


def _codes(display: Display, level: int) -> np.ndarray:
    """A flat image of device code `level` for `display`."""
    info = display.info
    return np.full((info.height_px, info.width_px), level,
                   np.uint8 if info.bit_depth == 8 else np.uint16)


def _fire(camera: Camera, settings: CameraSettings, trigger_box: Any) -> None:
    if settings.trigger_mode == "hardware" and trigger_box is not None:
        trigger_box.fire()
    else:
        camera.trigger()


def grab_after(camera: Camera, clock: Clock, settings: CameraSettings, on: float, count: int,
               timeout_s: float = 1.0, trigger_box: Any = None,
               margin_s: float = 1e-3) -> list[Frame]:
    """`count` frames whose exposure starts at or after `on` (stale ones are skipped)."""
    if clock.now() < on:
        clock.sleep_until(on)
    camera.flush()
    triggered = settings.trigger_mode != "free-running"
    if triggered:  # one margin later, so timestamp jitter cannot look earlier than `on`
        clock.sleep_until(on + margin_s)
    for _ in range(count if triggered else 0):
        _fire(camera, settings, trigger_box)
    frames: list[Frame] = []
    lost = 0
    while len(frames) < count:
        try:
            fr = camera.grab(timeout_s)
        except FrameLost:  # that trigger's frame is gone on the link: trigger once more
            lost += 1
            if lost > MAX_LOST_FRAMES:
                raise
            _fire(camera, settings, trigger_box)
            continue
        if fr.timestamp_s >= on:
            frames.append(fr)
    return frames


def grab_settled(display: Display, camera: Camera, clock: Clock, settings: CameraSettings,
                 image: np.ndarray, settle_s: float, average: int = 1,
                 trigger_box: Any = None) -> np.ndarray:
    """Show `image`, wait `settle_s` after its flip, return the mean of `average` frames."""
    flip = display.show(image)
    frames = grab_after(camera, clock, settings, flip + settle_s, average, trigger_box=trigger_box)
    return np.mean([f.image for f in frames], axis=0, dtype=np.float64)


def _lit_mask(white: np.ndarray, dark: np.ndarray, what: str) -> np.ndarray:
    """Pixels that see the screen (white clearly above dark); error if the screen is not seen."""
    contrast = white - dark
    top = float(np.percentile(contrast, 99))
    lit = contrast > 0.25 * top
    if top <= 0 or lit.sum() < 16:
        raise AcquisitionError(f"{what}: the camera does not see the screen (white-dark "
                               f"contrast {top:.1f} DN); check the pose, exposure and display")
    return lit


# Lead in summed squared error the chosen latency needs over every other candidate: one
# frame off by 0.3 of the white-dark step. Less means the frames cannot tell them apart.
MIN_SEPARATION = 0.09


def measure_latency(display: Display, camera: Camera, clock: Clock, settings: CameraSettings,
                    *, max_periods: int = 8, trials: int = 3, rounds: int = 4,
                    trigger_box: Any = None) -> LatencyResult:
    """Latency in whole refresh periods from dark->white flips and frames sampling the switch.

    Each frame's brightness fraction f (lit pixels, 0 = dark, 1 = white) is compared
    with what each candidate latency L predicts for its exposure [t, t + e]: the mean
    over the exposure of a ramp from 0 at F + LP to 1 at F + (L+1)P (scan-out). The
    candidate with the smallest squared error wins, but only by `MIN_SEPARATION`: a slow
    host (late wake-ups, slow grabs) can leave no frame inside the switch, and then several
    latencies fit equally well. Undecided candidates get one frame each at the middle of
    their ramp, one switch per frame, for up to `rounds` rounds; those still undecided are
    returned in `undecided` (`decided_latency` refuses them). `violations` counts frames off
    by more than 0.2 from the chosen prediction.
    """
    info = display.info
    p = 1.0 / info.refresh_hz
    top = (1 << info.bit_depth) - 1
    applied = camera.configure(settings)
    e = applied.exposure_s
    camera.start()
    rel: list[float] = []
    frac: list[float] = []
    try:
        settle = (max_periods + 2) * p
        dark_img = grab_settled(display, camera, clock, applied, _codes(display, 0), settle,
                                trigger_box=trigger_box)
        white_img = grab_settled(display, camera, clock, applied, _codes(display, top), settle,
                                 trigger_box=trigger_box)
        lit = _lit_mask(white_img, dark_img, "latency measurement")
        d, w = float(dark_img[lit].mean()), float(white_img[lit].mean())

        def switch(wait: float) -> float:
            """Dark, settled (`wait` more), then white: the white flip."""
            flip = display.show(_codes(display, 0))
            clock.sleep_until(flip + settle + wait)
            camera.flush()
            return display.show(_codes(display, top))

        def record(frames: list[Frame], flip: float) -> None:
            rel.extend(f.timestamp_s - flip for f in frames)
            frac.extend((float(f.image[lit].mean()) - d) / (w - d) for f in frames)

        for trial in range(trials):
            flip = switch(trial * p / trials)
            record(_sample_switch(camera, clock, applied, flip, settle + e, trigger_box), flip)
        err, pred = _latency_fit(rel, frac, p, e, max_periods)
        for _ in range(rounds):
            undecided = _undecided(err)
            if len(undecided) == 1:
                break
            for c in undecided:  # one frame mid-ramp of each: it tells c from c +- 1
                flip = switch(0.0)
                record(_sample_at(camera, clock, applied, flip, flip + (c + 0.5) * p - e / 2,
                                  settle + e, trigger_box), flip)
            err, pred = _latency_fit(rel, frac, p, e, max_periods)
    finally:
        camera.stop()
    undecided = _undecided(err)
    best = undecided[0]
    violations = int((np.abs(np.asarray(frac) - pred[best]) > 0.2).sum())
    return LatencyResult(best * p, best, len(rel), violations, tuple(sorted(undecided[1:])))


def decided_latency(display: Display, camera: Camera, clock: Clock, settings: CameraSettings,
                    *, trigger_box: Any = None) -> LatencyResult:
    """`measure_latency`, or `AcquisitionError` when its frames fit other latencies about as
    well: a capture timed with a wrong latency pairs every pattern with the wrong frame."""
    res = measure_latency(display, camera, clock, settings, trigger_box=trigger_box)
    if res.undecided:
        raise AcquisitionError(
            f"latency measurement: {res.observations} frames fit latencies of "
            f"{sorted((res.periods, *res.undecided))} refresh periods about equally (no frame "
            "was exposed early enough after the flips to see the switch: an overloaded host, "
            "or a camera slow to start after a trigger); retry on a quieter host or give the "
            "latency (ControllerOptions.latency_s)")
    return res


def _latency_fit(rel: list[float], frac: list[float], p: float, e: float, max_periods: int
                 ) -> tuple[np.ndarray, np.ndarray]:
    """Summed squared error of each candidate latency 0..max_periods, and its predictions."""
    t, f = np.asarray(rel)[None, :], np.asarray(frac)[None, :]
    cand = np.arange(max_periods + 1)[:, None]

    def ramp_integral(x: np.ndarray) -> np.ndarray:
        return np.where(x < 0, 0.0, np.where(x < 1, x * x / 2, x - 0.5))

    x0, x1 = t / p - cand, (t + e) / p - cand
    pred = (ramp_integral(x1) - ramp_integral(x0)) * p / e
    return ((f - pred) ** 2).sum(axis=1), pred


def _undecided(err: np.ndarray) -> list[int]:
    """Candidates within `MIN_SEPARATION` of the best fit (the best first)."""
    best = int(np.argmin(err))
    return [best] + [int(c) for c in np.flatnonzero(err - err[best] < MIN_SEPARATION)
                     if c != best]


def _sample_at(camera: Camera, clock: Clock, settings: CameraSettings, flip: float, at: float,
               span_s: float, trigger_box: Any) -> list[Frame]:
    """Triggered: one frame exposed from `at` (or as soon after as the host manages).
    Free-running: the frames of the stream from `flip` to `flip + span_s`."""
    if settings.trigger_mode == "free-running":
        return _sample_switch(camera, clock, settings, flip, span_s, trigger_box)
    clock.sleep_until(at)
    _fire(camera, settings, trigger_box)
    return _grab_unless_lost(camera)


def _sample_switch(camera: Camera, clock: Clock, settings: CameraSettings, flip: float,
                   span_s: float, trigger_box: Any) -> list[Frame]:
    """Frames exposed from `flip` to `flip + span_s`: triggered every max(P/3, e + 1 ms)."""
    camera.flush()
    frames: list[Frame] = []
    if settings.trigger_mode == "free-running":
        while True:
            fr = camera.grab(1.0)
            if fr.timestamp_s > flip + span_s:
                return frames
            if fr.timestamp_s >= flip:
                frames.append(fr)
    step = settings.exposure_s + 1e-3
    n = max(1, math.ceil(span_s / step))
    for k in range(n):
        clock.sleep_until(flip + k * step)
        _fire(camera, settings, trigger_box)
        frames.extend(_grab_unless_lost(camera))
    return frames


def _grab_unless_lost(camera: Camera) -> list[Frame]:
    """The frame of the trigger just fired, or none when the link lost it: a sample of the
    switch is taken at one moment, so a lost one cannot be re-taken and the fit uses the rest."""
    try:
        return [camera.grab(1.0)]
    except FrameLost:
        return []


def _max_dn(settings: CameraSettings, camera: Camera) -> int:
    """Top DN of the configured pixel format (Mono12 -> 4095), else the camera's bit depth."""
    m = re.search(r"(\d+)$", settings.pixel_format)
    bits = int(m.group(1)) if m else camera.info.bit_depth
    return (1 << bits) - 1


def choose_exposure(display: Display, camera: Camera, clock: Clock, settings: CameraSettings,
                    *, latency_s: float, target: float = 0.8, percentile: float = 99.9,
                    tolerance: float = 0.05, max_iterations: int = 8,
                    trigger_box: Any = None) -> ExposureResult:
    """Exposure putting the white flat's `percentile` at `target` x max DN (no saturation).

    Saturated frames shrink the exposure 4x; otherwise it is scaled by target/level.
    Free-running cameras are limited to one frame period.
    """
    top = (1 << display.info.bit_depth) - 1
    settle = latency_s + 2.0 / display.info.refresh_hz
    s = settings
    level, frac = 0.0, 0.0
    for it in range(1, max_iterations + 1):
        s = camera.configure(s)
        max_dn = _max_dn(s, camera)
        camera.start()
        try:
            img = grab_settled(display, camera, clock, s, _codes(display, top), settle,
                               trigger_box=trigger_box)
        finally:
            camera.stop()
        level = float(np.percentile(img, percentile))
        frac = level / max_dn
        if abs(frac - target) <= tolerance * target:
            return ExposureResult(s, level, frac, it)
        factor = 0.25 if frac >= 0.98 else target / max(frac, 1e-3)
        limit = 1.0 / s.frame_rate_hz if s.trigger_mode == "free-running" and s.frame_rate_hz \
            else 10.0
        new_e = float(np.clip(s.exposure_s * factor, 1e-5, limit))
        if new_e == s.exposure_s:
            return ExposureResult(s, level, frac, it)
        s = replace(s, exposure_s=new_e)
    raise AcquisitionError(f"exposure: no exposure within {tolerance:.0%} of {target:.0%} of max "
                           f"DN after {max_iterations} tries (last {s.exposure_s:.5f} s gave "
                           f"{frac:.1%}); is the scene changing?")


def measure_display_response(display: Display, camera: Camera, clock: Clock,
                             settings: CameraSettings, *, latency_s: float,
                             levels: np.ndarray | None = None, average: int = 2,
                             trigger_box: Any = None) -> DisplayResponse:
    """Display response from flat grey levels: mean over lit pixels, normalized 0..1.

    Use settings whose white flat is not saturated (`choose_exposure`).
    """
    top = (1 << display.info.bit_depth) - 1
    lv = np.unique(np.linspace(0, top, 18).round().astype(int)) if levels is None \
        else np.unique(np.asarray(levels, int))
    if lv[0] != 0 or lv[-1] != top:
        lv = np.unique(np.concatenate([[0], lv, [top]]))
    settle = latency_s + 2.0 / display.info.refresh_hz
    applied = camera.configure(settings)
    camera.start()
    try:
        imgs = [grab_settled(display, camera, clock, applied, _codes(display, int(v)), settle,
                             average, trigger_box) for v in lv]
    finally:
        camera.stop()
    lit = _lit_mask(imgs[-1], imgs[0], "display response")
    means = np.array([im[lit].mean() for im in imgs])
    if means[-1] >= 0.98 * _max_dn(applied, camera):
        raise AcquisitionError("display response: the white flat saturates; reduce the exposure "
                               "(choose_exposure) first")
    linear = np.maximum.accumulate(np.clip((means - means[0]) / (means[-1] - means[0]), 0, 1))
    return DisplayResponse(lv.astype(np.float64), linear)


def pose_latency(rig: Rig, given_s: float | None, settings: CameraSettings) -> float:
    """Flip-to-panel latency for a pose: given, kept on the rig, or measured now (and kept)."""
    if given_s is not None:
        return given_s
    if rig.latency_s is None:
        rig.latency_s = decided_latency(rig.display, rig.camera, rig.clock, settings).latency_s
    return rig.latency_s
