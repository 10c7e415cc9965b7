"""Jobs: every long operation of the service as a typed object.

- `model`: `JobStatus`, `JobKind`, `JobState` (what the API shows) and `Job`, the base of
  every job definition (kind, resource, claims; `run`, then `succeeded`/`ended` on its
  resource in the job's final transaction);
- `manager`: `JobManager` creates, drives, tracks, cancels and recovers jobs;
- `poses` (capture, decode of imported frames, re-decode), `calibrations` (one model, or a
  batch), `intrinsics`: the job definitions the routes start after validating a request.
"""

from api.jobs.manager import JobManager
from api.jobs.model import Job, JobKind, JobState, JobStatus

__all__ = ["Job", "JobKind", "JobManager", "JobState", "JobStatus"]
