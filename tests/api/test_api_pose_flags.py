"""A capture whose integrity check flags it is stored as a `flagged` pose with the reason."""

from types import SimpleNamespace

from api.jobs.poses import PoseJob


class _OneRecord:
    def __init__(self, record):
        self.record = record

    def get(self, _model, _pid):
        return self.record


def _finish(result):
    pose = SimpleNamespace(status="decoding", error=None, frames_done=0)
    job = PoseJob(svc=None, session_id="ses_0123456789abcdef", pose_id="pose_0123456789abcdef")
    job.succeeded(_OneRecord(pose), result)
    return pose


def test_flagged_capture_becomes_flagged_pose_with_reason():
    pose = _finish({"capture": {"captured": 50, "flagged": "camera or screen moved"},
                    "decode": {"valid_pixels": 10, "width": 4, "height": 3}, "frames": 50})
    assert pose.status == "flagged"
    assert pose.error == "integrity check: camera or screen moved"
    assert pose.valid_pixels == 10


def test_clean_capture_is_ready():
    pose = _finish({"capture": {"captured": 50}, "decode": {"valid_pixels": 10}, "frames": 50})
    assert pose.status == "ready" and pose.error is None
