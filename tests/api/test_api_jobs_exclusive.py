"""One active job per pose and per calibration, even for simultaneous requests; the stored
progress of a stopped capture equals the frames on disk."""

from __future__ import annotations

import threading
import time
from pathlib import Path

import pytest
from fastapi.testclient import TestClient

from api.app import create_app
from api.config import ServiceConfig
from api.db import (
    Database,
    JobRecord,
    PoseRecord,
    SessionRecord,
    TargetRigCalibrationRecord,
)
from api.jobs import JobManager
from api.pose_path import stored_indices
from api.problems import Problem
from api.recovery import mark_interrupted
from api.worker.executor import InProcessExecutor
from tests.api.test_api_session import screen_poses, small_rig
from tests.api.test_api_units import FnJob


def _wait(c: TestClient, job_id: str, cond, timeout_s: float = 120) -> dict:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        j = c.get(f"/jobs/{job_id}").json()
        if cond(j):
            return j
        time.sleep(0.05)
    raise AssertionError(f"job {job_id}: condition not reached")


def test_simultaneous_resumes_start_one_job(tmp_path: Path) -> None:
    data = tmp_path / "data"
    app = create_app(ServiceConfig(data_dir=data, executor="threads"))
    with TestClient(app) as c:
        rig = c.post("/rigs", json={"name": "slow", "config": small_rig(slow=True)}).json()
        sess = c.post("/sessions", json={"rig_id": rig["id"], "preset": "fast"}).json()
        job = c.post(f"/sessions/{sess['id']}/poses",
                     json={"screen_pose": screen_poses(1, 5)[0]}).json()
        _wait(c, job["id"], lambda j: j["stage"] == "capture" and j["done"] >= 3)
        assert c.post(f"/jobs/{job['id']}/cancel").status_code == 202
        final = _wait(c, job["id"], lambda j: j["status"] not in ("queued", "running"))
        assert final["status"] == "cancelled"
        pose = c.get(final["resource"]).json()
        on_disk = len(stored_indices(data / "poses" / pose["id"]))
        assert on_disk >= 3 and pose["frames_done"] == on_disk

        barrier = threading.Barrier(3)
        answers: list[int] = []

        def resume() -> None:
            barrier.wait()
            answers.append(c.post(f"{final['resource']}/resume").status_code)

        threads = [threading.Thread(target=resume) for _ in range(3)]
        for t in threads:
            t.start()
        for t in threads:
            t.join(60)
        assert sorted(answers) == [202, 409, 409], answers
        jobs = c.get("/jobs", params={"kind": "capture"}).json()["items"]
        mine = [j for j in jobs if j["resource"] == final["resource"] and j["id"] != job["id"]]
        assert len(mine) == 1
        done = _wait(c, mine[0]["id"], lambda j: j["status"] not in ("queued", "running"), 300)
        assert done["status"] == "succeeded", done["error"]


def test_job_claims_are_exclusive_until_the_job_ends(tmp_path: Path) -> None:
    db = Database(tmp_path / "x.db")
    ex = InProcessExecutor(max_workers=1)
    jm = JobManager(db, ex)
    gate = threading.Event()
    claim = ("cal_0000000000000001",)
    fn = FnJob(kind_="calibrate", resource="/calibrations/cal_0000000000000001", claims=claim,
               body=lambda ctx: gate.wait(10) and {})
    with db.claim_session() as s:
        first = jm.create(s, fn)
    with pytest.raises(Problem) as err, db.claim_session() as s:
        jm.create(s, FnJob(kind_="calibrate", claims=claim))
    assert err.value.status == 409 and first.id in err.value.detail
    jm.start(first.id, fn)
    gate.set()
    deadline = time.monotonic() + 10
    while jm.get(first.id)["status"] != "succeeded":
        assert time.monotonic() < deadline
        time.sleep(0.01)
    with db.claim_session() as s:  # the claim ended with the job
        jm.create(s, FnJob(kind_="calibrate", claims=claim))
    assert jm.recover("restart") != []
    with db.claim_session() as s:  # recovery drops the claims of interrupted jobs
        jm.create(s, FnJob(kind_="calibrate", claims=claim))
    ex.shutdown()
    db.close()


def test_job_created_in_a_failed_transaction_is_forgotten(tmp_path: Path) -> None:
    """A route that fails after `create` leaves neither a row, a claim nor a live entry."""
    db = Database(tmp_path / "x.db")
    jm = JobManager(db, InProcessExecutor(max_workers=1))
    claim = ("cal_0000000000000002",)
    with pytest.raises(RuntimeError), db.claim_session() as s:
        state = jm.create(s, FnJob(kind_="calibrate", claims=claim))
        raise RuntimeError("route failed after creating the job")
    assert jm.active_ids() == [] and jm.get(state.id) is None
    with db.claim_session() as s:  # the claim went with the rolled-back transaction
        kept = jm.create(s, FnJob(kind_="calibrate", claims=claim))
    assert jm.active_ids() == [kept.id]
    jm.executor.shutdown()
    db.close()


def test_recovery_sets_capture_progress_to_frames_on_disk(tmp_path: Path) -> None:
    db = Database(tmp_path / "x.db")
    with db.session() as s:
        s.add(SessionRecord(id="ses_0000000000000001", name="", plan={}, created_at=0.0))
    with db.session() as s:
        s.add(JobRecord(id="job_0000000000000001", kind="capture", status="running",
                        stage="capture", done=7, total=30, created_at=0.0))
        s.add(PoseRecord(id="pose_0000000000000001", session_id="ses_0000000000000001",
                         index=0, source="capture", status="capturing",
                         job_id="job_0000000000000001", frames_done=7, created_at=0.0))
    mark_interrupted(db, ["job_0000000000000001"], "restart", lambda pid: 14)
    with db.session() as s:
        assert s.get(PoseRecord, "pose_0000000000000001").frames_done == 14
        assert s.get(JobRecord, "job_0000000000000001").done == 14
        assert s.get(PoseRecord, "pose_0000000000000001").status == "interrupted"
    db.close()


def test_recovery_marks_a_target_rig_calibration_cut_off_by_a_restart(tmp_path: Path) -> None:
    """Left `running`, it would read as working for ever and hold its views from deletion."""
    db = Database(tmp_path / "x.db")
    with db.session() as s:
        s.add(TargetRigCalibrationRecord(
            id="cal_0000000000000001", cameras={}, reference="A", camera_models={"A": "opencv5"},
            status="running", job_id="job_0000000000000001", created_at=0.0))
    mark_interrupted(db, ["job_0000000000000001"], "the server restarted")
    with db.session() as s:
        rec = s.get(TargetRigCalibrationRecord, "cal_0000000000000001")
        assert (rec.status, rec.error) == ("interrupted", "the server restarted")
    db.close()
