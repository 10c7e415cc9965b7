"""The model registry is the one list of models: the API's model enum and per-model options
schema come from it, and a bad option or too few poses is a 422 at the request (nothing is
stored, no job starts)."""

from __future__ import annotations

import time
from pathlib import Path

import pytest
from fastapi.testclient import TestClient

from api.app import create_app
from api.config import ServiceConfig
from api.db import PoseRecord
from api.store import new_id
from calibration.fit.registry import MODEL_NAMES, MODELS, model_spec

PLAN = {
    "format": "phasecal.plan/1",
    "screen": {"width_px": 64, "height_px": 48, "pitch_mm": [0.5, 0.5]},
    "frames": [
        {"kind": "flat", "level": 1.0},
        {"kind": "flat", "level": 0.0},
        *[{"kind": "cosine", "axis": a, "period_px": 80.0, "step": s, "steps": 4}
          for a in "xy" for s in range(4)],
    ],
}


@pytest.fixture
def client(tmp_path: Path):
    with TestClient(create_app(ServiceConfig(data_dir=tmp_path / "data"))) as c:
        yield c


def _session_with_ready_poses(client: TestClient, n: int) -> str:
    """A session whose `n` poses are decoded (records only: nothing here reads their maps)."""
    r = client.post("/sessions", json={"name": "reg", "plan": PLAN})
    assert r.status_code == 201, r.text
    sid = r.json()["id"]
    with client.app.state.services.db.session() as s:
        for i in range(n):
            s.add(PoseRecord(id=new_id("pose"), session_id=sid, index=i, source="import",
                             status="ready", width=64, height=48, valid_pixels=3072,
                             frames_done=10, created_at=time.time()))
    return sid


def test_registry_entries_are_consistent() -> None:
    for name, spec in MODELS.items():
        assert spec.name == name and spec.model_class.type_name == name
        assert callable(spec.fit) and spec.min_poses >= 3
        assert spec.parse_options({}) == spec.options()  # every option has a default
    with pytest.raises(ValueError, match=r"options\.cells: .*expected \[cu, cv\]"):
        model_spec("sgcc").parse_options({"cells": "banana"})
    with pytest.raises(ValueError, match=r"unknown key\(s\) \['grid'\]"):
        model_spec("sgcc").parse_options({"grid": [24, 16]})
    with pytest.raises(ValueError, match="model: expected one of"):
        model_spec("nonesuch")


def test_openapi_lists_every_model_and_its_options(client: TestClient) -> None:
    doc = client.get("/openapi.json").json()
    schemas = doc["components"]["schemas"]
    mapping = schemas["CalibrationCreate"]["discriminator"]["mapping"]
    assert sorted(mapping) == sorted(MODEL_NAMES)
    assert sorted(schemas["Calibration"]["properties"]["model"]["enum"]) == sorted(MODEL_NAMES)
    for name, spec in MODELS.items():
        request = schemas[mapping[name].rsplit("/", 1)[1]]
        assert request["properties"]["options"]["$ref"].endswith("/" + spec.options.__name__)
        assert set(schemas[spec.options.__name__]["properties"]) == set(spec.options.model_fields)
    assert {"cells", "xp", "max_iterations"} <= set(schemas["SgccOptions"]["properties"])


@pytest.mark.parametrize(("body", "field"), [
    ({"model": "sgcc", "options": {"cells": "banana"}}, "options.cells"),
    ({"model": "opencv5", "options": {"grid": [24, 16]}}, "options.grid"),
    ({"model": "raygrid", "options": {"central": "no"}}, "options.central"),
    ({"model": "sgcc-noncentral", "options": {"xp": "torch"}}, "options.xp"),
    ({"model": "opencv-rational", "options": {"outlier_rounds": -1}}, "options.outlier_rounds"),
    ({"model": "nonesuch"}, "model"),
])
def test_bad_options_are_422_naming_the_field(client: TestClient, body: dict, field: str) -> None:
    sid = _session_with_ready_poses(client, 3)
    r = client.post(f"/sessions/{sid}/calibrations", json=body)
    assert r.status_code == 422, r.text
    assert r.headers["content-type"] == "application/problem+json"
    assert field in r.json()["detail"]
    assert client.get("/calibrations").json() == [] and client.get("/jobs").json()["total"] == 0


def test_too_few_poses_is_422_at_the_request(client: TestClient) -> None:
    sid = _session_with_ready_poses(client, 2)
    for model in MODEL_NAMES:
        r = client.post(f"/sessions/{sid}/calibrations", json={"model": model})
        assert r.status_code == 422, (model, r.text)
        assert r.json()["detail"] == f"pose_ids: {model} needs >= 3 training poses, got 2"
    r = client.post("/batches/calibrations", json={"session_ids": [sid],
                                                   "models": [{"model": "sgcc"}]})
    assert r.status_code == 422 and "session_ids" in r.json()["detail"]
    assert client.get("/calibrations").json() == []


def test_batch_options_are_typed(client: TestClient) -> None:
    sid = _session_with_ready_poses(client, 3)
    r = client.post("/batches/calibrations", json={
        "session_ids": [sid], "models": [{"model": "sgcc", "options": {"grid": [24, 16]}}]})
    assert r.status_code == 422 and "options.grid" in r.json()["detail"]
    assert client.get("/calibrations").json() == []
