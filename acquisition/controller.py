"""Acquisition controller: run one pose's pattern sequence, pipelined, with verified frames.

Sync method: every frame is checked by TIME, on the shared clock. `Display.show`
returns the flip time F; with the measured flip-to-panel latency L (setup helper) and
the scan-out period P, a pattern is fully on the panel from F + L + P until the next
pattern's flip F' + L. A frame is accepted only if its exposure [t, t + e] (camera
timestamp = start of exposure) lies inside [F + L + P + m, F' + L - m], m = timestamp
uncertainty margin. Frames starting earlier are stale (dropped silently); frames ending
later are torn (the pattern is re-shown and re-captured); a triggered frame the camera
reports lost on its link (`FrameLost`: an incomplete buffer) is re-shown and re-captured
the same way, at once rather than after the grab timeout. A consistency check rejects
frames whose sequence number does not increase (re-delivered buffers). Timing is used
rather than image content because content checks cannot tell adjacent phase steps of
a low-contrast pattern apart reliably and cost a full image comparison per frame,
whereas timestamps decide exactly and for free; the end-of-pose reference repeats
(`acquisition.integrity`) catch what timing cannot (motion, flicker, drift).

Pipelining: the next pattern is submitted so that it reaches the panel right after the
current exposure is predicted to end (triggered: trigger time + exposure; free-running:
the camera's frame grid predicted from the last timestamp), so per pattern the sequence
costs about ceil((P + e + 2m) / P) refresh periods instead of latency + P + e + readout.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Sequence
from dataclasses import replace
from typing import Any

import numpy as np

from acquisition.clock import Clock
from acquisition.errors import AcquisitionError, CameraDisconnected, CameraTimeout, FrameLost
from acquisition.integrity import IntegrityReport, compare_references, reference_indices
from acquisition.pattern_cache import cache_for
from acquisition.pose_types import (
    AcceptedFrame,
    ControllerOptions,
    PoseCapture,
    Recapture,
    Status,
)
from acquisition.protocols import Camera, CameraSettings, Display, Frame
from acquisition.rig import Rig
from acquisition.setup import pose_latency
from acquisition.sinks import FrameSink
from acquisition.stream_statistics import ReportsStreamStatistics, StreamStatistics
from acquisition.usb.trigger_box import TriggerSink
from calibration.shared.plan import Plan
from calibration.shared.progress import Cancel, Cancelled, Progress, is_cancelled

SHOW_LEAD = 0.75  # refresh periods before its vsync a show is called (blocks until then)


class _Failed(AcquisitionError):
    """Internal: the pose cannot be completed (message is the reason)."""


def _slow_max(observed: float, previous: float, cap: float) -> float:
    """A cost estimate: the largest recent observation, decaying slowly, at most `cap`."""
    return min(max(observed, 0.9 * previous), cap)


class _Runner:
    """State of one pose capture (devices, timing estimates, counters)."""

    def __init__(self, display: Display, camera: Camera, clock: Clock, settings: CameraSettings,
                 plan: Plan, opts: ControllerOptions, latency_s: float, trigger: TriggerSink | None,
                 cancel: Cancel) -> None:
        self.display, self.camera, self.clock, self.plan = display, camera, clock, plan
        self.settings, self.opts, self.lat, self.trigger_box = settings, opts, latency_s, trigger
        self.cancel = cancel
        self.period = 1.0 / display.info.refresh_hz
        fps = settings.frame_rate_hz or 30.0
        self.frame_period = 1.0 / fps
        self.triggered = settings.trigger_mode in ("software", "hardware")
        self.recaptures: list[Recapture] = []
        self.stale = 0
        self.reconnects = 0
        self.lost = 0  # triggered frames that came back incomplete and were triggered again
        self.late_s = 0.0  # the latest trigger after its planned time (a stall: torn frames)
        self.trigger_lag_s = 0.0  # learned delay from a trigger to its exposure's start
        self.last_seq = -1
        self.fr_ref: tuple[float, int] | None = None  # (timestamp, sequence) of a recent frame
        self.delivery_s = 0.0  # learned delay from an exposure's end to its frame's arrival
        self.collect_cost = 0.0  # learned time to grab, check and accept an arrived frame
        self.render_cost = 0.0  # learned time to render a pattern's device codes
        self._codes: dict[int, np.ndarray] = {}
        self.patterns, self.digest = cache_for(display), plan.digest()  # codes across poses

    # -- devices ----------------------------------------------------------------------
    def codes(self, index: int) -> np.ndarray:
        """Device codes of plan frame `index` (the two rendered last are kept)."""
        if index not in self._codes:
            if len(self._codes) >= 2:
                del self._codes[next(iter(self._codes))]
            t0 = self.clock.now()
            self._codes[index] = self.patterns.codes(
                self.plan, self.digest, index, bit_depth=self.display.info.bit_depth,
                response=self.opts.response, dither=self.opts.dither)
            self.render_cost = _slow_max(self.clock.now() - t0, self.render_cost, self.period)
        return self._codes[index]

    def show(self, index: int) -> float:
        """Show plan frame `index`; returns its flip time."""
        return self.display.show(self.codes(index))

    def check_cancel(self) -> None:
        """Raise `Cancelled` once the user asked to stop."""
        if is_cancelled(self.cancel):
            raise Cancelled("cancelled by the user")

    def fire(self) -> None:
        """One trigger: the trigger box in 'hardware' mode when present, else software."""
        if self.settings.trigger_mode == "hardware" and self.trigger_box is not None:
            self.trigger_box.fire()
        else:
            self.camera.trigger()

    def restart(self) -> None:
        """Restart the stream after a timeout (drops whatever the driver holds)."""
        self.camera.stop()
        self.camera.start()
        self.last_seq = -1
        self.fr_ref = None

    def reconnect(self, error: CameraDisconnected) -> None:
        """Reconnect with exponential back-off; `_Failed` after `max_reconnects` tries."""
        delay = self.opts.backoff_s
        last: Exception = error
        for _ in range(self.opts.max_reconnects):
            self.check_cancel()
            self.clock.sleep_until(self.clock.now() + delay)
            delay *= 2
            try:
                self.camera.reconnect()
                self.camera.configure(self.settings)
                self.camera.start()
            except CameraDisconnected as exc:
                last = exc
                continue
            self.reconnects += 1
            self.last_seq, self.fr_ref = -1, None
            return
        raise _Failed(f"camera disconnected and {self.opts.max_reconnects} reconnect attempts "
                      f"failed: {last}")

    def rephase(self, index: int) -> None:
        """Free-running: restart the stream until its frames fall inside pattern windows.

        With a camera frame period that is a whole number of refresh periods, the offset x
        of the camera's exposure starts past a pattern's on-time is fixed modulo P. One
        pattern per camera frame needs x <= P - 2m - e; otherwise every pattern waits a
        refresh more (1.5x-2x the vsync floor). Stream start sets the phase, so restart at a
        start time chosen to put x in the middle of the window, using the start-to-frame
        delay measured on the previous restart. Best effort: faults leave the phase as is.
        """
        p, m, e = self.period, self.opts.margin_s, self.settings.exposure_s
        ratio = self.frame_period / p
        window = p - 2 * m - e
        if abs(ratio - round(ratio)) > 1e-3 or window <= 0:
            return  # the phase drifts anyway, or no exposure fits a refresh
        try:
            delay: float | None = None
            for attempt in range(self.opts.rephase_attempts + 1):
                flip = self.show(index)
                self.camera.flush()
                fr = self.camera.grab(self.opts.grab_timeout_s)
                self.last_seq, self.fr_ref = fr.sequence, (fr.timestamp_s, fr.sequence)
                x = (fr.timestamp_s - (flip + self.lat + p + m)) % p
                if x <= window or attempt == self.opts.rephase_attempts:
                    return
                self.camera.stop()
                if delay is not None:
                    # next start whose first frame lands mid-window on the vsync grid
                    target = flip + self.lat + p + m + window / 2 - delay
                    now = self.clock.now()
                    self.clock.sleep_until(target + math.ceil((now - target) / p) * p)
                started = self.clock.now()
                self.camera.start()
                first = self.camera.grab(self.opts.grab_timeout_s)
                delay = (first.timestamp_s - started) % self.frame_period
                self.last_seq, self.fr_ref = first.sequence, (first.timestamp_s, first.sequence)
        except (CameraTimeout, CameraDisconnected):
            self.last_seq, self.fr_ref = -1, None  # run() recovers from faults itself

    # -- one pattern ------------------------------------------------------------------
    def predicted_end(self, on: float) -> float:
        """Predicted end of the exposures of a pattern fully visible from `on`."""
        k, e = self.opts.average, self.settings.exposure_s
        if self.triggered:  # triggered one margin after `on`: timestamp jitter stays inside
            start = max(self.clock.now(), on + self.opts.margin_s)
            return start + k * (e + max(self.opts.trigger_overhead_s, self.trigger_lag_s))
        if self.fr_ref is None:
            return on + k * self.frame_period + e
        ts, _ = self.fr_ref
        first = ts + math.ceil((on - ts) / self.frame_period) * self.frame_period
        return first + (k - 1) * self.frame_period + e

    def begin_exposures(self, on: float, flush: bool) -> float:
        """Wait until `on` (triggered: one margin later, in one sleep, as every wake-up may
        be late); flush stale frames if allowed; trigger the pattern's exposures. Returns
        the time the first trigger fired (free-running: the time the wait ended)."""
        start = on + self.opts.margin_s if self.triggered else on
        if self.clock.now() < start:
            self.clock.sleep_until(start)
            if flush:
                self.camera.flush()
        fired = self.clock.now()
        if self.triggered:
            self.late_s = max(self.late_s, fired - start)
            for _ in range(self.opts.average):
                self.fire()
        return fired

    def next_flip_target(self, flip: float, end: float) -> float:
        """Earliest vsync (on the grid of `flip`) at which the next pattern may flip."""
        need = end + self.opts.margin_s - self.lat
        return flip + max(1, math.ceil((need - flip) / self.period - 1e-9)) * self.period

    def learn_delivery(self, asked: float, end: float) -> None:
        """Learn the delay from an exposure's end to its frame's arrival (readout, transfer)
        from grabs that waited for their frame."""
        now = self.clock.now()
        if now - asked > 1e-4 and now > end:
            self.delivery_s = _slow_max(now - end, self.delivery_s, self.period)

    def collect(self, on: float, off: float, fired: float) -> tuple[list[Frame], str]:
        """Grab `average` frames exposed inside [on, off] of the pattern triggered at
        `fired`; ([], reason) if one is torn."""
        frames: list[Frame] = []
        while len(frames) < self.opts.average:
            self.check_cancel()
            fr = self.camera.grab(self.opts.grab_timeout_s)
            if fr.sequence <= self.last_seq:
                self.stale += 1  # re-delivered buffer: inconsistent, never accepted
                continue
            self.last_seq = fr.sequence
            self.fr_ref = (fr.timestamp_s, fr.sequence)
            if fr.timestamp_s < on:
                self.stale += 1
                continue
            if not frames and self.triggered:  # a camera that polls for triggers, holds
                # back overlapping ones, or a busy host: retries must wait for the lag
                self.trigger_lag_s = _slow_max(fr.timestamp_s - fired, self.trigger_lag_s,
                                               self.opts.grab_timeout_s)
            if fr.timestamp_s + fr.exposure_s > off:
                return [], (f"torn: exposure {fr.timestamp_s:.4f}+{fr.exposure_s:.4f} s ran past "
                            f"the next pattern at {off + self.opts.margin_s:.4f} s")
            frames.append(fr)
        return frames, ""

    def run(self, order: Sequence[int], accept: Callable[[int, np.ndarray, AcceptedFrame], None]
            ) -> None:
        """Capture `order`, each position's accepted frame handed to `accept` once (a torn
        pattern is shown again after the others, so an index repeated in `order` arrives in
        order of its positions, other indices in any order).

        Event loop over three kinds of timed actions, earliest first: show the next
        pattern (so it flips right after the last shown pattern's exposures end), begin
        the exposures of the oldest shown pattern (at its on-screen time), collect the
        frames of the oldest begun pattern (once its frames should have arrived, and the
        next flip, which bounds its window, is known: a show due earlier goes first, so a
        blocking grab never makes a flip miss its vsync). Several patterns can be in flight
        when the latency exceeds the exposure.
        """
        m = self.opts.margin_s
        order = list(order)  # torn patterns are appended to be shown again
        if not self.triggered and self.opts.rephase_attempts > 0 and order:
            self.rephase(order[0])
        attempts: dict[int, int] = {}
        pos = 0  # next position of `order` to show
        done = 0  # positions accepted
        inflight: list[dict[str, Any]] = []  # shown, not yet accepted; oldest first
        while done < len(order):
            self.check_cancel()
            now = self.clock.now()
            unbegun = [f for f in inflight if not f["begun"]]
            t_show = t_flip = math.inf  # when to call show, and the vsync it flips at
            if pos < len(order):
                if inflight:
                    last = inflight[-1]
                    t_flip = self.next_flip_target(last["flip"], last["end"])
                    t_show = t_flip - SHOW_LEAD * self.period  # late wake-ups still flip
                else:
                    t_show = t_flip = now
            t_begin = unbegun[0]["on"] if unbegun else math.inf
            deadline = min(t_show, t_begin) - 2 * m  # the next action bound to a vsync
            head = inflight[0] if inflight and inflight[0]["begun"] else None
            bounded = head is not None and (len(inflight) > 1 or pos >= len(order))
            t_collect = head["end"] + self.delivery_s if bounded and head is not None \
                else math.inf  # when the frames should have arrived
            try:
                if t_collect < math.inf and (max(now, t_collect) + self.collect_cost <= deadline
                                             or len(inflight) - len(unbegun) > 1
                                             or deadline == math.inf):
                    pass  # collect now: it ends before the next timed action
                elif (pos < len(order) and order[pos] not in self._codes
                      and now + self.render_cost <= deadline):
                    self.codes(order[pos])  # render the next pattern in idle time
                    continue
                elif t_flip <= t_begin:  # a show blocks until its flip: no trigger inside
                    self.clock.sleep_until(t_show)
                    i = order[pos]
                    flip = self.show(i)
                    on = flip + self.lat + self.period + m
                    inflight.append({"index": i, "flip": flip, "on": on, "begun": False,
                                     "end": self.predicted_end(on)})
                    pos += 1
                    continue
                else:
                    entry = unbegun[0]
                    entry["fired"] = self.begin_exposures(entry["on"], flush=entry is inflight[0])
                    entry["end"] = self.predicted_end(entry["on"])
                    entry["begun"] = True
                    continue
                assert head is not None
                off = inflight[1]["flip"] + self.lat - m if len(inflight) > 1 else math.inf
                asked = self.clock.now()
                frames, reason = self.collect(head["on"], off, head["fired"])
                self.learn_delivery(asked, head["end"])
            except FrameLost as exc:  # the camera is in step: its frame alone is gone
                frames, reason = [], f"lost: {exc}"
                self.lost += 1
            except CameraTimeout as exc:
                frames, reason = [], f"timeout: {exc}"
                self.restart()
            except CameraDisconnected as exc:
                frames, reason = [], f"disconnected: {exc}"
                self.reconnect(exc)
            if not frames:
                failed = order[done]  # the oldest pattern not yet accepted
                self.recaptures.append(Recapture(failed, reason))
                tries = attempts.pop(done, 0) + 1  # by position: indices may repeat
                if tries >= self.opts.max_attempts:
                    raise _Failed(f"plan frame {failed}: no valid frame after "
                                  f"{self.opts.max_attempts} attempts (last: {reason})")
                if reason.startswith(("torn", "lost")) and head is not None:
                    # the camera is in step: the patterns in flight stay valid, and the
                    # torn or lost one is shown again after the others (frames still due
                    # for it predate the next pattern's window: dropped as stale)
                    order.append(failed)
                    attempts[len(order) - 1] = tries
                    inflight.pop(0)
                    done += 1
                else:  # the stream restarted: re-show from the failed pattern on
                    attempts[done] = tries
                    pos = done
                    inflight = []
                continue
            image = frames[0].image if len(frames) == 1 else \
                np.mean([f.image for f in frames], axis=0, dtype=np.float32)
            accept(head["index"], image,
                   AcceptedFrame(frames[0].sequence, frames[0].timestamp_s, head["flip"]))
            self.collect_cost = _slow_max(self.clock.now() - max(asked, t_collect),
                                          self.collect_cost, self.period)
            inflight.pop(0)
            done += 1


def capture_pose(
    rig: Rig,
    plan: Plan,
    sink: FrameSink,
    *,
    indices: Sequence[int] | None = None,
    options: ControllerOptions | None = None,
    settings: CameraSettings | None = None,
    progress: Callable[[Progress], None] | None = None,
    cancelled: Cancel = None,
) -> PoseCapture:
    """Capture plan frames `indices` (default all) of one pose on `rig` into `sink`.

    `settings` default to the rig's; the rig's measured display response (gamma LUT) is
    used unless `options.response` is given, and its flip-to-panel latency is measured on
    the first capture and kept on the rig (`Rig.latency_s`) unless `options.latency_s` is.
    Never raises for camera faults, cancel or integrity problems: see `status`/`reason`.
    """
    opts = options or ControllerOptions()
    if opts.response is None and rig.display_response is not None:
        opts = replace(opts, response=rig.display_response)  # measured once per rig
    display, camera, clock = rig.display, rig.camera, rig.clock
    settings = settings or rig.settings
    order = list(range(len(plan.frames))) if indices is None else [int(i) for i in indices]
    if len(set(order)) != len(order) or any(not 0 <= i < len(plan.frames) for i in order):
        raise ValueError(f"indices: expected distinct plan frame indices 0..{len(plan.frames) - 1}")
    applied = camera.configure(settings)
    latency = pose_latency(rig, opts.latency_s, applied)
    started = clock.now()
    wall0 = time.monotonic()
    runner = _Runner(display, camera, clock, applied, plan, opts, latency, rig.trigger, cancelled)
    refs = reference_indices(plan) if opts.integrity else None
    if refs is not None and not all(r in order for r in refs):
        refs = None  # a resumed capture without the references cannot repeat them
    repeats: dict[int, np.ndarray] = {}  # the references again, right after the plan frames
    originals: dict[int, np.ndarray] = {}
    accepted: list[int] = []
    frames: dict[int, AcceptedFrame] = {}
    stream0: StreamStatistics | None = None  # the camera's transfer counters before the pose
    if isinstance(camera, ReportsStreamStatistics):
        stream0 = camera.stream_statistics()

    def accept(i: int, image: np.ndarray, info: AcceptedFrame) -> None:
        if i in frames:  # a reference seen before: this is its repeat
            repeats[i] = image
            return
        sink.add(i, image)
        accepted.append(i)
        frames[i] = info
        if refs is not None and i in refs:
            originals[i] = np.array(image, copy=True)
        if progress is not None:
            done = len(accepted)
            eta = (time.monotonic() - wall0) / done * (len(order) - done)
            progress(Progress(done, len(order), eta, "capture" if done < len(order)
                              else "integrity"))

    def result(status: Status, reason: str, report: IntegrityReport | None = None) -> PoseCapture:
        stream = None
        if stream0 is not None and isinstance(camera, ReportsStreamStatistics):
            stream = camera.stream_statistics().since(stream0)
        return PoseCapture(status, reason, len(order), accepted, frames, runner.recaptures,
                           runner.stale, runner.reconnects, latency, started, clock.now(), report,
                           runner.late_s, lost_frames=runner.lost, stream=stream)

    camera.start()
    try:  # one pipelined run: the repeats follow the last plan frame without a restart
        runner.run(order + list(refs or ()), accept)
        report = None
        if refs is not None:
            report = compare_references(tuple(originals[r] for r in refs),  # type: ignore[arg-type]
                                        tuple(repeats[r] for r in refs),  # type: ignore[arg-type]
                                        opts.thresholds)
            report = IntegrityReport(report.ok, report.reasons, report.metrics, tuple(refs))
            if not report.ok:
                return result("flagged", report.reason, report)
        return result("complete", "", report)
    except Cancelled:
        return result("cancelled", f"cancelled after {len(accepted)} of {len(order)} frames "
                                   "(see `accepted` for which)")
    except _Failed as exc:
        return result("failed", str(exc))
    finally:
        try:
            camera.stop()
        except CameraDisconnected:
            pass
