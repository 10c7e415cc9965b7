"""The typed client (sync and async) against a real `phasecal serve` subprocess: success,
failed and cancelled jobs with problem details, SSE waiting, streamed upload memory (retries
and the protocol core without a server: tests/api/test_client_core.py)."""

from __future__ import annotations

import asyncio
import gc
import importlib.util
import tracemalloc
import zipfile
from pathlib import Path
from typing import get_type_hints

import cv2
import numpy as np
import pytest

from api import schemas
from api.client import (
    AsyncPhasecalClient,
    JobCancelled,
    JobFailed,
    PhasecalClient,
    ServiceError,
)
from api.client import types as ct
from tests.api.test_api_session import screen_poses, small_rig
from tests.api_server import ServerProcess


@pytest.fixture(scope="module")
def server(tmp_path_factory: pytest.TempPathFactory):
    srv = ServerProcess(tmp_path_factory.mktemp("client") / "data")
    srv.start()
    yield srv
    srv.stop()


@pytest.fixture(scope="module")
def client(server: ServerProcess):
    with PhasecalClient(server.url) as c:
        yield c


@pytest.fixture(scope="module")
def session(client: PhasecalClient) -> ct.Session:
    rig = client.create_rig("small", small_rig())
    return client.create_session("client", rig_id=rig["id"], preset="fast")


@pytest.fixture(scope="module")
def poses(client: PhasecalClient, session: ct.Session) -> list[str]:
    ids = []
    for pose in screen_poses(3, seed=11):
        seen: list[ct.Job] = []
        job = client.wait(client.capture_pose(session, pose), timeout_s=300,
                          on_progress=seen.append)
        assert job["status"] == "succeeded" and job["resource"]
        assert seen and all(j["id"] == job["id"] for j in seen)  # progress came over SSE
        ids.append(job["resource"].rsplit("/", 1)[-1])
    return ids


@pytest.mark.parametrize(("typed", "model"), [
    (ct.Job, schemas.Job), (ct.Session, schemas.Session), (ct.Pose, schemas.Pose),
    (ct.Calibration, schemas.Calibration), (ct.Rig, schemas.Rig)])
def test_typed_answers_match_the_server_schemas(typed, model):
    assert set(get_type_hints(typed)) == set(model.model_fields)


def test_calibrate_wait_and_streamed_downloads(client, session, poses, tmp_path):
    assert [p["id"] for p in client.list_poses(session)] == poses
    job = client.wait(client.calibrate(session, "opencv5", pose_ids=poses), timeout_s=300)
    cal = client.get_calibration(job["resource"].rsplit("/", 1)[-1])
    assert cal["status"] == "succeeded" and cal["stats"]["rms_px"] < 0.5
    model_path = client.download_file(cal, "model.json", tmp_path / "model.json")
    assert '"opencv5"' in model_path.read_text()
    info = client.export(cal, "opencv-yaml", tmp_path / "cam.yaml")
    assert info == {"exact": True}
    fs = cv2.FileStorage(str(tmp_path / "cam.yaml"), cv2.FILE_STORAGE_READ)
    assert fs.getNode("camera_matrix").mat().shape == (3, 3)
    fs.release()
    info = client.export(cal, "remap", tmp_path / "remap.npz", pinhole=[100, 100, 80, 60, 160, 120])
    assert np.load(tmp_path / "remap.npz")["map_x"].shape == (120, 160)
    out = client.undistort_points(cal, [[80.0, 60.0]])
    assert len(out["pixels"]) == 1
    client.download_maps(session, poses[0], tmp_path / "maps.npz")
    assert (tmp_path / "maps.npz").stat().st_size > 1000
    with zipfile.ZipFile(client.download_frames(session, poses[0], tmp_path / "f.zip")) as zf:
        names = zf.namelist()
    assert len(names) == session["frame_count"] and names[0] == "frame_0000.png"
    assert not list(tmp_path.glob("*.part"))


def test_failed_request_and_failed_job_carry_problem_details(client, session, poses):
    with pytest.raises(ServiceError) as err:
        client.get_session("ses_0000000000000000")
    assert err.value.status == 404 and err.value.type.endswith("/not-found")
    assert err.value.problem["title"] == "Not found" and "does not exist" in err.value.detail
    with pytest.raises(ServiceError) as err:
        client.export("cal_0000000000000000", "ros", "/nonexistent/x.yaml")
    assert err.value.status == 404
    with pytest.raises(ServiceError) as err:  # a malformed option never becomes a job
        client.calibrate(session, "sgcc", pose_ids=poses, options={"xp": "torch"})
    assert err.value.status == 422 and "options.xp" in err.value.detail
    if importlib.util.find_spec("cupy") is not None:
        pytest.skip("CuPy is installed: an xp=cupy fit would not fail")
    job = client.calibrate(session, "sgcc", pose_ids=poses, options={"xp": "cupy"})
    with pytest.raises(JobFailed) as err:  # well-formed, but this machine cannot run it
        client.wait(job, timeout_s=300)
    assert not isinstance(err.value, JobCancelled)
    assert err.value.job["status"] == "failed" and err.value.job_status == "failed"
    assert "options.xp: 'cupy' requested but not importable" in err.value.detail
    assert err.value.problem["instance"] == f"/jobs/{job['id']}"
    assert err.value.type.endswith("/job-failed")


def _slow_capture(client: PhasecalClient) -> ct.Job:
    rig = client.create_rig("slow", small_rig(slow=True))
    sess = client.create_session(rig_id=rig["id"], preset="fast")
    return client.capture_pose(sess, screen_poses(1, 5)[0])


def test_cancel_then_wait_raises_cancelled(client):
    job = client.cancel_job(_slow_capture(client))
    with pytest.raises(JobCancelled) as err:
        client.wait(job, timeout_s=120)
    assert err.value.job["status"] == "cancelled"
    with pytest.raises(ServiceError) as again:
        client.cancel_job(job)
    assert again.value.status == 409


def test_async_client_and_task_cancellation(server, client, session, poses):
    async def scenario() -> tuple[ct.Job, ct.Calibration]:
        async with AsyncPhasecalClient(server.url) as ac:
            assert (await ac.health())["status"] == "ok"
            job = await ac.wait(await ac.calibrate(session, "opencv5", pose_ids=poses),
                                timeout_s=300)
            cal = await ac.get_calibration(job["resource"].rsplit("/", 1)[-1])
            slow = _slow_capture(client)
            task = asyncio.create_task(ac.wait(slow, timeout_s=300))
            # cancelled while it follows the job (the slow capture takes ~1.5 s when idle:
            # a fixed wait of 1 s could see it finish first on a fast machine)
            await asyncio.sleep(0.2)
            assert (await ac.get_job(slow["id"]))["status"] in ("queued", "running")
            task.cancel()
            with pytest.raises(asyncio.CancelledError):
                await task
            # the cancelled wait cancelled the server's job
            with pytest.raises(JobCancelled):
                await ac.wait(slow, timeout_s=120)
            return slow, cal

    slow, cal = asyncio.run(scenario())
    assert cal["status"] == "succeeded"
    assert client.get_job(slow)["status"] == "cancelled"


def test_large_upload_is_streamed_with_flat_memory(client, session, tmp_path):
    big = tmp_path / "frames.npy"
    frames = np.lib.format.open_memmap(big, mode="w+", dtype=np.uint8, shape=(40, 1200, 1600))
    frames[:] = 7
    del frames
    size = big.stat().st_size
    assert size > 75e6
    gc.collect()
    tracemalloc.start()
    try:
        with pytest.raises(ServiceError) as err:  # the frames do not match the plan
            client.import_frames(session, [big])
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert err.value.status in (409, 422), err.value.detail
    assert peak < 8e6, f"client peak {peak / 1e6:.1f} MB for a {size / 1e6:.0f} MB upload"


def test_upload_of_a_missing_file_names_it(client, session):
    with pytest.raises(FileNotFoundError, match=r"nope\.npy"):
        client.import_frames(session, [Path("nope.npy")])
