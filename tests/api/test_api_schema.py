"""Property-based check of the whole OpenAPI document with schemathesis: no 5xx, no violation."""

from __future__ import annotations

import tempfile
import time
from pathlib import Path

import pytest
import schemathesis
from fastapi.testclient import TestClient
from hypothesis import HealthCheck, settings
from schemathesis import checks

from api.app import create_app
from api.config import ServiceConfig

_DATA = Path(tempfile.mkdtemp(prefix="phasecal-schemathesis-"))
APP = create_app(ServiceConfig(data_dir=_DATA, max_upload_bytes=1 << 20))
schema = schemathesis.openapi.from_asgi("/openapi.json", APP)
# Generous per-request limit: correctness is checked here, not speed. Guidance (GET
# next-pose) fits a model on first request and takes seconds on a loaded 2-core machine.
_TIMEOUT_S = 120


@schema.parametrize()
@settings(max_examples=25, deadline=None, derandomize=True,
          suppress_health_check=list(HealthCheck))
def test_openapi_conformance(case: schemathesis.Case) -> None:
    # positive_data_acceptance is excluded: semantic rules (a plan's completeness, ids that
    # exist, plan xor preset) cannot be written in JSON Schema and rightly answer 4xx.
    case.call_and_validate(excluded_checks=[checks.positive_data_acceptance], timeout=_TIMEOUT_S)


# The same fuzzing with the ids of real resources (a session with imported maps, its poses,
# an sGCC calibration, its job, the default rig), so cases get past the 404 for unknown ids
# and reach body validation, project/unproject on a fitted model, maps and previews.
# Operations that start captures or fits, delete the fixtures or stream without end stay in
# the run above.
# Schemathesis runs an app's lifespan when it loads the schema, and the shutdown stops the
# app's executor: the fixture creates the resources through a second app on the same data
# directory (records in SQLite, files on disk), which the fuzzed app then serves.
_LIVE_CONFIG = ServiceConfig(data_dir=Path(tempfile.mkdtemp(prefix="phasecal-live-")),
                             max_upload_bytes=1 << 20)
LIVE_APP = create_app(_LIVE_CONFIG)
LIVE = schemathesis.openapi.from_asgi("/openapi.json", LIVE_APP).exclude(method="DELETE").exclude(
    path_regex=r"/(poses|poses/import|poses/\{pose_id\}/resume|calibrations)$",
    method="POST").exclude(path="/batches/calibrations").exclude(
    # next-pose fits a model on the executor (tests/api/test_guidance_api.py checks it)
    path_regex=r"/next-pose(\.png)?$").exclude(
    # The live MJPEG preview is an endless stream by design (bounded only by `frames`);
    # tests/api/test_live_capture.py checks it with bounded streams.
    path="/rigs/{rig_id}/camera/preview")


@pytest.fixture(scope="module")
def live_ids() -> dict[str, str]:
    from tests.api.test_api_uploads import PLAN, good_maps

    c = TestClient(create_app(_LIVE_CONFIG))  # no lifespan: its executor stays up
    sess = c.post("/sessions", json={"plan": PLAN.to_dict()}).json()
    poses = [c.post(f"/sessions/{sess['id']}/poses/import-maps",
                    files={"file": ("m.npz", good_maps(20 + k, size=(160, 120)).to_npz_bytes())}
                    ).json()["id"] for k in range(3)]
    job = c.post(f"/sessions/{sess['id']}/calibrations", json={"model": "sgcc"}).json()
    while job["status"] in ("queued", "running"):
        time.sleep(0.1)
        job = c.get(f"/jobs/{job['id']}").json()
    assert job["status"] == "succeeded", job["error"]
    return {"session_id": sess["id"], "pose_id": poses[0], "job_id": job["id"],
            "cal_id": job["resource"].rsplit("/", 1)[-1], "rig_id": c.get("/rigs").json()[0]["id"]}


@LIVE.parametrize()
@settings(max_examples=40, deadline=None, derandomize=True,
          suppress_health_check=list(HealthCheck))
def test_openapi_conformance_on_live_resources(case: schemathesis.Case,
                                               live_ids: dict[str, str]) -> None:
    for key in list(case.path_parameters or {}):
        if key in live_ids:
            case.path_parameters[key] = live_ids[key]
    case.call_and_validate(excluded_checks=[checks.positive_data_acceptance], timeout=_TIMEOUT_S)


def test_openapi_document_is_complete() -> None:
    doc = APP.openapi()
    paths = doc["paths"]
    for path in ("/sessions", "/sessions/{session_id}/poses", "/sessions/{session_id}/poses/import",
                 "/sessions/{session_id}/calibrations", "/calibrations/{cal_id}/unproject",
                 "/jobs", "/jobs/{job_id}/events", "/jobs/{job_id}/cancel", "/rigs", "/devices"):
        assert path in paths, path
    examples = doc["components"]["schemas"]["CalibrationCreate"].get("examples")
    assert examples and examples[0]["model"] == "opencv-rational"
