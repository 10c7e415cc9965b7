"""Transfer counters of a camera's image stream, for cameras whose link can lose data.

GigE Vision sends each frame as UDP packets (GVSP); a busy link or host drops some, the
driver asks the camera to resend them, and a frame whose packets still miss is lost. A
backend that can tell offers `stream_statistics()` (the `ReportsStreamStatistics`
protocol); the controller puts the counters of one pose into its result, so a capture
report shows how much of its recaptures the link caused.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, fields
from typing import Protocol, runtime_checkable


@dataclass(frozen=True)
class StreamStatistics:
    """Counters since a camera was opened (across stream restarts); `since` gives a span."""

    completed_frames: int = 0  # buffers filled completely
    incomplete_frames: int = 0  # buffers closed with data missing: frames lost
    missing_frames: int = 0  # frames of which not a single packet arrived (frame id gaps)
    received_packets: int = 0
    missing_packets: int = 0  # packets still missing when their frame was given up
    resend_requests: int = 0  # packets asked for again
    resent_packets: int = 0  # packets recovered by a resend
    packet_resend: bool = False  # whether the stream asks for lost packets again

    def since(self, earlier: StreamStatistics) -> StreamStatistics:
        """The counts accumulated after `earlier` was read (`packet_resend` as now)."""
        counts = {name: getattr(self, name) - getattr(earlier, name) for name in COUNTS}
        return StreamStatistics(**counts, packet_resend=self.packet_resend)

    def plus(self, later: StreamStatistics) -> StreamStatistics:
        """These counts and those of `later` (a stream that followed), `packet_resend` as
        `later`'s."""
        counts = {name: getattr(self, name) + getattr(later, name) for name in COUNTS}
        return StreamStatistics(**counts, packet_resend=later.packet_resend)

    def as_dict(self) -> dict[str, int | bool]:
        """Plain counters for JSON reports."""
        return asdict(self)


COUNTS = tuple(f.name for f in fields(StreamStatistics) if f.name != "packet_resend")


@runtime_checkable
class ReportsStreamStatistics(Protocol):
    """A camera that counts its stream's transfers (optional beside `Camera`)."""

    def stream_statistics(self) -> StreamStatistics: ...
