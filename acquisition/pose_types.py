"""What the acquisition controller takes and returns for one pose: options, per-frame
timing, recaptures and the pose's result (kept apart so callers need not import the loop)."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Literal

from acquisition.integrity import IntegrityReport, IntegrityThresholds
from acquisition.patterns import DisplayResponse
from acquisition.stream_statistics import StreamStatistics

Status = Literal["complete", "cancelled", "failed", "flagged"]


@dataclass(frozen=True)
class ControllerOptions:
    """How to run a pose; `latency_s` None means measure it first (setup helper)."""

    latency_s: float | None = None
    average: int = 1  # frames averaged per pattern (float32 mean when > 1)
    margin_s: float = 1e-3  # timestamp uncertainty allowed on each side of the window
    trigger_overhead_s: float = 1e-3  # trigger latency + gap between triggered exposures
    grab_timeout_s: float = 1.0
    max_attempts: int = 6  # captures tried per pattern before failing
    max_reconnects: int = 5
    backoff_s: float = 0.1  # first reconnect delay, doubled each failure
    response: DisplayResponse | None = None  # gamma pre-compensation for the patterns
    dither: str | None = "ordered"
    integrity: bool = True
    thresholds: IntegrityThresholds = field(default_factory=IntegrityThresholds)
    rephase_attempts: int = 3  # free-running: stream restarts to put frames in the windows


@dataclass(frozen=True)
class Recapture:
    """One rejected capture attempt of a plan frame and why."""

    index: int
    reason: str
    camera: str = ""  # the camera whose frame it was (a rig's camera name)


@dataclass(frozen=True)
class AcceptedFrame:
    """Timing of an accepted frame (first one if averaged)."""

    sequence: int
    timestamp_s: float
    flip_s: float


@dataclass
class PoseCapture:
    """Result of one pose: which plan frames were accepted, recaptures, timing, integrity."""

    status: Status
    reason: str
    total: int
    accepted: list[int]
    frames: dict[int, AcceptedFrame]
    recaptures: list[Recapture]
    stale_dropped: int
    reconnects: int
    latency_s: float
    started_s: float
    finished_s: float
    integrity: IntegrityReport | None = None
    # the latest any trigger fired after its planned time (triggered modes): a stall of the
    # capture machine longer than the pattern's exposure window tears that pattern's frame
    trigger_late_s: float = 0.0
    # triggered frames that came back incomplete (packets lost on the link) and were
    # triggered again; each is also a `Recapture` whose reason starts with "lost"
    lost_frames: int = 0
    # the camera's transfer counters over this pose, when the camera offers them
    stream: StreamStatistics | None = None
    # each camera's own result by name, the reference first (one entry for one camera)
    cameras: dict[str, PoseCapture] = field(default_factory=dict)

    @classmethod
    def combined(cls, per_camera: dict[str, PoseCapture]) -> PoseCapture:
        """A pose of several cameras from their results (which share status, unless a
        camera's integrity check flagged it): accepted are the plan frames every camera
        has, the frames' timing is the reference's, the counters are summed."""
        results = list(per_camera.values())
        first = results[0]
        flagged = {n: r for n, r in per_camera.items() if r.status == "flagged"}
        status, reason = first.status, first.reason
        if status == "complete" and flagged:
            status = "flagged"
            reason = "; ".join(f"camera {n!r}: {r.reason}" for n, r in flagged.items())
        everywhere = set.intersection(*(set(r.accepted) for r in results))
        integrity = next((r.integrity for r in flagged.values()), first.integrity)
        return cls(status, reason, first.total, [i for i in first.accepted if i in everywhere],
                   first.frames, [c for r in results for c in r.recaptures],
                   sum(r.stale_dropped for r in results), sum(r.reconnects for r in results),
                   first.latency_s, first.started_s, max(r.finished_s for r in results),
                   integrity, first.trigger_late_s, sum(r.lost_frames for r in results),
                   None, dict(per_camera))

    def counters(self) -> dict[str, Any]:
        """Recapture and transfer counts for a capture report (JSON-ready), with each
        camera's on a rig of several."""
        out: dict[str, Any] = {"recaptures": len(self.recaptures),
                               "lost_frames": self.lost_frames}
        if self.stream is not None:
            out["stream"] = self.stream.as_dict()
        if len(self.cameras) > 1:
            out["cameras"] = {n: r.counters() for n, r in self.cameras.items()}
        return out

    @property
    def accepted_count(self) -> int:
        """Number of plan frames handed to the sink."""
        return len(self.accepted)

    @property
    def duration_s(self) -> float:
        """Clock time the sequence took (virtual or real)."""
        return self.finished_s - self.started_s
