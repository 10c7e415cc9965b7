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
from collections.abc import Callable, Mapping, Sequence
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


class _Lane:
    """One camera of a pose capture: its device, settings, stream state and counters."""

    def __init__(self, name: str, camera: Camera, settings: CameraSettings) -> None:
        self.name, self.camera, self.settings = name, camera, settings
        self.frame_period = 1.0 / (settings.frame_rate_hz or 30.0)
        self.triggered = settings.trigger_mode in ("software", "hardware")
        self.stale = 0
        self.reconnects = 0
        self.lost = 0  # triggered frames that came back incomplete and were triggered again
        self.trigger_lag_s = 0.0  # learned delay from a trigger to its exposure's start
        self.last_seq = -1
        self.fr_ref: tuple[float, int] | None = None  # (timestamp, sequence) of a recent frame
        self.fault: CameraTimeout | CameraDisconnected | None = None  # met while triggering
        self.recaptures: list[Recapture] = []


class _Runner:
    """State of one pose capture (display, the cameras' lanes, timing estimates, counters).

    Every pattern is shown once for all cameras; a camera whose frame of it is torn or lost
    gets the pattern shown again later, for the cameras that still need it."""

    def __init__(self, display: Display, lanes: list[_Lane], clock: Clock, plan: Plan,
                 opts: ControllerOptions, latency_s: float, trigger: TriggerSink | None,
                 cancel: Cancel) -> None:
        self.display, self.lanes, self.clock, self.plan = display, lanes, clock, plan
        self.opts, self.lat, self.trigger_box = opts, latency_s, trigger
        self.cancel = cancel
        self.period = 1.0 / display.info.refresh_hz
        self.triggered = any(lane.triggered for lane in lanes)
        self.late_s = 0.0  # the latest trigger after its planned time (a stall: torn frames)
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

    def fire(self, lanes: list[_Lane]) -> None:
        """One trigger for each of `lanes`: the trigger box once for the cameras in
        'hardware' mode when present, software triggers for the others (free-running
        cameras need none). A fault is kept on its lane for its collect to handle."""
        box = self.trigger_box is not None and any(
            lane.settings.trigger_mode == "hardware" for lane in lanes)
        if box:
            assert self.trigger_box is not None
            self.trigger_box.fire()
        for lane in lanes:
            if not lane.triggered or (box and lane.settings.trigger_mode == "hardware"):
                continue
            try:
                lane.camera.trigger()
            except (CameraTimeout, CameraDisconnected) as exc:
                lane.fault = lane.fault or exc

    def restart(self, lane: _Lane) -> None:
        """Restart a stream after a timeout (drops whatever the driver holds)."""
        lane.camera.stop()
        lane.camera.start()
        lane.last_seq = -1
        lane.fr_ref = None

    def reconnect(self, lane: _Lane, error: CameraDisconnected) -> None:
        """Reconnect with exponential back-off; `_Failed` after `max_reconnects` tries."""
        delay = self.opts.backoff_s
        last: Exception = error
        for _ in range(self.opts.max_reconnects):
            self.check_cancel()
            self.clock.sleep_until(self.clock.now() + delay)
            delay *= 2
            try:
                lane.camera.reconnect()
                lane.camera.configure(lane.settings)
                lane.camera.start()
            except CameraDisconnected as exc:
                last = exc
                continue
            lane.reconnects += 1
            lane.last_seq, lane.fr_ref = -1, None
            return
        raise _Failed(f"{self.named(lane)}disconnected and {self.opts.max_reconnects} "
                      f"reconnect attempts failed: {last}")

    def named(self, lane: _Lane) -> str:
        """How a reason names the camera: 'camera' alone, or with its name on a rig of
        several."""
        return "camera " if len(self.lanes) == 1 else f"camera {lane.name!r} "

    def rephase(self, lane: _Lane, index: int) -> None:
        """Free-running: restart the stream until its frames fall inside pattern windows.

        With a camera frame period that is a whole number of refresh periods, the offset x
        of the camera's exposure starts past a pattern's on-time is fixed modulo P. One
        pattern per camera frame needs x <= P - 2m - e; otherwise every pattern waits a
        refresh more (1.5x-2x the vsync floor). Stream start sets the phase, so restart at a
        start time chosen to put x in the middle of the window, using the start-to-frame
        delay measured on the previous restart. Best effort: faults leave the phase as is.
        Each free-running camera of a rig is put in phase on its own.
        """
        p, m, e = self.period, self.opts.margin_s, lane.settings.exposure_s
        ratio = lane.frame_period / p
        window = p - 2 * m - e
        if abs(ratio - round(ratio)) > 1e-3 or window <= 0:
            return  # the phase drifts anyway, or no exposure fits a refresh
        camera = lane.camera
        try:
            delay: float | None = None
            for attempt in range(self.opts.rephase_attempts + 1):
                flip = self.show(index)
                camera.flush()
                fr = camera.grab(self.opts.grab_timeout_s)
                lane.last_seq, lane.fr_ref = fr.sequence, (fr.timestamp_s, fr.sequence)
                x = (fr.timestamp_s - (flip + self.lat + p + m)) % p
                if x <= window or attempt == self.opts.rephase_attempts:
                    return
                camera.stop()
                if delay is not None:
                    # next start whose first frame lands mid-window on the vsync grid
                    target = flip + self.lat + p + m + window / 2 - delay
                    now = self.clock.now()
                    self.clock.sleep_until(target + math.ceil((now - target) / p) * p)
                started = self.clock.now()
                camera.start()
                first = camera.grab(self.opts.grab_timeout_s)
                delay = (first.timestamp_s - started) % lane.frame_period
                lane.last_seq, lane.fr_ref = first.sequence, (first.timestamp_s, first.sequence)
        except (CameraTimeout, CameraDisconnected):
            lane.last_seq, lane.fr_ref = -1, None  # run() recovers from faults itself

    # -- one pattern ------------------------------------------------------------------
    def predicted_end(self, on: float, lanes: list[_Lane]) -> float:
        """Predicted end of the exposures of `lanes` of a pattern fully visible from `on`."""
        return max(self.lane_end(on, lane) for lane in lanes)

    def lane_end(self, on: float, lane: _Lane) -> float:
        """Predicted end of one camera's exposures of a pattern fully visible from `on`."""
        k, e = self.opts.average, lane.settings.exposure_s
        if lane.triggered:  # triggered one margin after `on`: timestamp jitter stays inside
            start = max(self.clock.now(), on + self.opts.margin_s)
            return start + k * (e + max(self.opts.trigger_overhead_s, lane.trigger_lag_s))
        if lane.fr_ref is None:
            return on + k * lane.frame_period + e
        ts, _ = lane.fr_ref
        first = ts + math.ceil((on - ts) / lane.frame_period) * lane.frame_period
        return first + (k - 1) * lane.frame_period + e

    def begin_exposures(self, on: float, flush: bool, lanes: list[_Lane]) -> float:
        """Wait until `on` (triggered: one margin later, in one sleep, as every wake-up may
        be late); flush stale frames if allowed; trigger the pattern's exposures on `lanes`.
        Returns the time the first trigger fired (free-running: the time the wait ended)."""
        start = on + self.opts.margin_s if self.triggered else on
        if self.clock.now() < start:
            self.clock.sleep_until(start)
            if flush:
                for lane in lanes:
                    try:
                        lane.camera.flush()
                    except (CameraTimeout, CameraDisconnected) as exc:
                        lane.fault = lane.fault or exc
        fired = self.clock.now()
        if self.triggered:
            self.late_s = max(self.late_s, fired - start)
            for _ in range(self.opts.average):
                self.fire(lanes)
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

    def collect(self, lane: _Lane, on: float, off: float, fired: float
                ) -> tuple[list[Frame], str]:
        """Grab `average` frames of one camera exposed inside [on, off] of the pattern
        triggered at `fired`; ([], reason) if one is torn."""
        if lane.fault is not None:  # met while flushing or triggering this pattern
            fault, lane.fault = lane.fault, None
            raise fault
        frames: list[Frame] = []
        while len(frames) < self.opts.average:
            self.check_cancel()
            fr = lane.camera.grab(self.opts.grab_timeout_s)
            if fr.sequence <= lane.last_seq:
                lane.stale += 1  # re-delivered buffer: inconsistent, never accepted
                continue
            lane.last_seq = fr.sequence
            lane.fr_ref = (fr.timestamp_s, fr.sequence)
            if fr.timestamp_s < on:
                lane.stale += 1
                continue
            if not frames and lane.triggered:  # a camera that polls for triggers, holds
                # back overlapping ones, or a busy host: retries must wait for the lag
                lane.trigger_lag_s = _slow_max(fr.timestamp_s - fired, lane.trigger_lag_s,
                                               self.opts.grab_timeout_s)
            if fr.timestamp_s + fr.exposure_s > off:
                return [], (f"torn: exposure {fr.timestamp_s:.4f}+{fr.exposure_s:.4f} s ran past "
                            f"the next pattern at {off + self.opts.margin_s:.4f} s")
            frames.append(fr)
        return frames, ""

    def collect_lane(self, lane: _Lane, on: float, off: float, fired: float
                     ) -> tuple[list[Frame], str, bool]:
        """`collect` with the camera's faults handled: (frames, reason, stream restarted)."""
        try:
            frames, reason = self.collect(lane, on, off, fired)
            return frames, reason, False
        except FrameLost as exc:  # the camera is in step: its frame alone is gone
            lane.lost += 1
            return [], f"lost: {exc}", False
        except CameraTimeout as exc:
            self.restart(lane)
            return [], f"timeout: {exc}", True
        except CameraDisconnected as exc:
            self.reconnect(lane, exc)
            return [], f"disconnected: {exc}", True

    def run(self, order: Sequence[int],
            accept: Callable[[_Lane, int, np.ndarray, AcceptedFrame], None]) -> None:
        """Capture `order` on every camera, each position's accepted frame handed to `accept`
        once per camera (a pattern torn or lost for some cameras is shown again after the
        others, for those cameras, so an index repeated in `order` arrives in order of its
        positions, other indices in any order).

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
        need = [list(self.lanes) for _ in order]  # by position: the cameras still needing it
        if self.opts.rephase_attempts > 0 and order:
            for lane in self.lanes:
                if not lane.triggered:
                    self.rephase(lane, order[0])
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
                                 "end": self.predicted_end(on, need[pos]), "lanes": need[pos]})
                pos += 1
                continue
            else:
                entry = unbegun[0]
                entry["fired"] = self.begin_exposures(entry["on"], entry is inflight[0],
                                                      entry["lanes"])
                entry["end"] = self.predicted_end(entry["on"], entry["lanes"])
                entry["begun"] = True
                continue
            assert head is not None
            off = inflight[1]["flip"] + self.lat - m if len(inflight) > 1 else math.inf
            asked = self.clock.now()
            bad: list[tuple[_Lane, str]] = []
            restarted = False
            for lane in list(head["lanes"]):  # (accepted cameras leave need[done])
                frames, reason, lane_restarted = self.collect_lane(lane, head["on"], off,
                                                                   head["fired"])
                restarted = restarted or lane_restarted
                if not frames:
                    bad.append((lane, reason))
                    continue
                image = frames[0].image if len(frames) == 1 else \
                    np.mean([f.image for f in frames], axis=0, dtype=np.float32)
                accept(lane, head["index"], image,
                       AcceptedFrame(frames[0].sequence, frames[0].timestamp_s, head["flip"]))
                need[done].remove(lane)
            if not restarted and not any(r.startswith("lost") for _, r in bad):
                self.learn_delivery(asked, head["end"])
            if not bad:
                self.collect_cost = _slow_max(self.clock.now() - max(asked, t_collect),
                                              self.collect_cost, self.period)
                inflight.pop(0)
                done += 1
                continue
            failed = order[done]  # the oldest pattern not yet accepted
            for lane, reason in bad:
                lane.recaptures.append(Recapture(failed, reason, lane.name))
            tries = attempts.pop(done, 0) + 1  # by position: indices may repeat
            if tries >= self.opts.max_attempts:
                lane, reason = bad[0]
                raise _Failed(f"plan frame {failed}"
                              f"{'' if len(self.lanes) == 1 else f' on camera {lane.name!r}'}"
                              f": no valid frame after {self.opts.max_attempts} attempts "
                              f"(last: {reason})")
            if not restarted:
                # the cameras are in step: the patterns in flight stay valid, and the torn
                # or lost one is shown again after the others for the cameras that need it
                # (frames still due for it predate the next pattern's window: dropped as stale)
                order.append(failed)
                need.append(need[done])
                attempts[len(order) - 1] = tries
                inflight.pop(0)
                done += 1
            else:  # a stream restarted: re-show from the failed pattern on
                attempts[done] = tries
                pos = done
                inflight = []


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
    """Capture plan frames `indices` (default all) of one pose on the rig's reference camera
    (a one-camera rig's camera) into `sink`; `capture_rig_pose` for every camera.

    `settings` default to the rig's; the rig's measured display response (gamma LUT) is
    used unless `options.response` is given, and its flip-to-panel latency is measured on
    the first capture and kept on the rig (`Rig.latency_s`) unless `options.latency_s` is.
    Never raises for camera faults, cancel or integrity problems: see `status`/`reason`.
    """
    name = rig.reference
    return capture_rig_pose(rig, plan, {name: sink}, indices=indices, options=options,
                            settings={name: settings} if settings is not None else None,
                            progress=progress, cancelled=cancelled)


class _LaneResult:
    """What one camera's frames of a pose came to (its sink, accepted frames, references)."""

    def __init__(self, sink: FrameSink) -> None:
        self.sink = sink
        self.accepted: list[int] = []
        self.frames: dict[int, AcceptedFrame] = {}
        self.originals: dict[int, np.ndarray] = {}
        self.repeats: dict[int, np.ndarray] = {}  # the references again, after the plan frames
        self.stream0: StreamStatistics | None = None  # transfer counters before the pose


def capture_rig_pose(
    rig: Rig,
    plan: Plan,
    sinks: Mapping[str, FrameSink],
    *,
    indices: Sequence[int] | None = None,
    options: ControllerOptions | None = None,
    settings: Mapping[str, CameraSettings] | None = None,
    progress: Callable[[Progress], None] | None = None,
    cancelled: Cancel = None,
) -> PoseCapture:
    """Capture plan frames `indices` (default all) of one pose on the cameras named by
    `sinks` (a subset of `rig.cameras`), each camera's frames into its sink, in sync: every
    pattern is shown once and every camera's frame of it checked by time (triggered by
    the trigger box or in software, or free-running and matched by timestamp); a pattern
    whose frame is torn or lost on some camera is shown again for those cameras.

    `settings` default to each camera's (`Rig.settings_for`). The result is the pose's
    overall outcome with each camera's in `PoseCapture.cameras`; flagged when any camera's
    integrity check fails. Never raises for camera faults, cancel or integrity problems.
    """
    if not sinks:
        raise ValueError("sinks: expected at least one camera's sink")
    unknown = [name for name in sinks if name not in rig.cameras]
    if unknown:
        raise ValueError(f"sinks: unknown camera(s) {unknown}; the rig has {list(rig.cameras)}")
    opts = options or ControllerOptions()
    if opts.response is None and rig.display_response is not None:
        opts = replace(opts, response=rig.display_response)  # measured once per rig
    clock = rig.clock
    order = list(range(len(plan.frames))) if indices is None else [int(i) for i in indices]
    if len(set(order)) != len(order) or any(not 0 <= i < len(plan.frames) for i in order):
        raise ValueError(f"indices: expected distinct plan frame indices 0..{len(plan.frames) - 1}")
    lanes = []
    for name in rig.cameras:  # the rig's order: the reference first
        if name in sinks:
            wanted = (settings or {}).get(name) or rig.settings_for(name)
            lanes.append(_Lane(name, rig.cameras[name], rig.cameras[name].configure(wanted)))
    # the flip-to-panel latency is the display's, measured with the reference camera
    latency = pose_latency(rig, opts.latency_s, lanes[0].settings
                           if lanes[0].name == rig.reference else rig.settings)
    started = clock.now()
    wall0 = time.monotonic()
    runner = _Runner(rig.display, lanes, clock, plan, opts, latency, rig.trigger, cancelled)
    refs = reference_indices(plan) if opts.integrity else None
    if refs is not None and not all(r in order for r in refs):
        refs = None  # a resumed capture without the references cannot repeat them
    results = {lane.name: _LaneResult(sinks[lane.name]) for lane in lanes}
    for lane in lanes:
        if isinstance(lane.camera, ReportsStreamStatistics):
            results[lane.name].stream0 = lane.camera.stream_statistics()
    total = len(order) * len(lanes)
    handed = 0

    def accept(lane: _Lane, i: int, image: np.ndarray, info: AcceptedFrame) -> None:
        nonlocal handed
        res = results[lane.name]
        if i in res.frames:  # a reference seen before: this is its repeat
            res.repeats[i] = image
            return
        res.sink.add(i, image)
        res.accepted.append(i)
        res.frames[i] = info
        if refs is not None and i in refs:
            res.originals[i] = np.array(image, copy=True)
        handed += 1
        if progress is not None:
            eta = (time.monotonic() - wall0) / handed * (total - handed)
            progress(Progress(handed, total, eta, "capture" if handed < total
                              else "integrity"))

    def lane_result(lane: _Lane, status: Status, reason: str) -> PoseCapture:
        res = results[lane.name]
        stream = None
        if res.stream0 is not None and isinstance(lane.camera, ReportsStreamStatistics):
            stream = lane.camera.stream_statistics().since(res.stream0)
        report = None
        if status == "complete" and refs is not None:
            report = compare_references(tuple(res.originals[r] for r in refs),  # type: ignore[arg-type]
                                        tuple(res.repeats[r] for r in refs),  # type: ignore[arg-type]
                                        opts.thresholds)
            report = IntegrityReport(report.ok, report.reasons, report.metrics, tuple(refs))
            if not report.ok:
                status, reason = "flagged", report.reason
        return PoseCapture(status, reason, len(order), res.accepted, res.frames,
                           lane.recaptures, lane.stale, lane.reconnects, latency, started,
                           clock.now(), report, runner.late_s, lost_frames=lane.lost,
                           stream=stream)

    def result(status: Status, reason: str) -> PoseCapture:
        per = {lane.name: lane_result(lane, status, reason) for lane in lanes}
        if len(per) == 1:
            only = next(iter(per.values()))
            return replace(only, cameras=per)
        return PoseCapture.combined(per)

    for lane in lanes:
        lane.camera.start()
    try:  # one pipelined run: the repeats follow the last plan frame without a restart
        runner.run(order + list(refs or ()), accept)
        return result("complete", "")
    except Cancelled:
        done = min(len(r.accepted) for r in results.values())
        return result("cancelled", f"cancelled after {done} of {len(order)} frames "
                                   "(see `accepted` for which)")
    except _Failed as exc:
        return result("failed", str(exc))
    finally:
        for lane in lanes:
            try:
                lane.camera.stop()
            except CameraDisconnected:
                pass
