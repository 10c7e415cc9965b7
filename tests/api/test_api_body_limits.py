"""Request bodies are bounded by what each route needs: JSON far below the upload limit, and
refused by shape before parsing when their objects would need many times their size."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from fastapi.testclient import TestClient

from acquisition.patterns import PRESETS, build_plan
from api.app import create_app
from api.body_limits import POINT_ROUTES, UPLOAD_ROUTES
from api.config import DEFAULT_MAX_JSON_BYTES, ServiceConfig
from api.schemas import (
    MAX_FRAME_KEYS,
    MAX_ID_LENGTH,
    MAX_PLAN_FRAMES,
    MAX_POINTS,
    MAX_RIG_CONFIG_KEYS,
    MAX_TREE_DEPTH,
    MAX_TREE_STRING,
)
from benchmarks.reliability_bodies import (
    MAX_GROWTH_MB,
    body_cases,
    legitimate_cases,
    run_body_cases,
)
from benchmarks.serve_process import start_serve
from tests.api.test_api_uploads import PLAN, good_maps

UNKNOWN_CAL = "/calibrations/cal_0000000000000000"
JSON = {"content-type": "application/json"}


@pytest.fixture(scope="module")
def client(tmp_path_factory: pytest.TempPathFactory):
    data = tmp_path_factory.mktemp("limits") / "data"
    with TestClient(create_app(ServiceConfig(data_dir=data, executor="threads")),
                    raise_server_exceptions=False) as c:
        yield c


def _problem(r, status: int) -> dict:
    assert r.status_code == status, r.text[:500]
    assert r.headers["content-type"].startswith("application/problem+json")
    return r.json()


def _plan_body(frames: bytes) -> bytes:
    return b'{"plan": {"format": "phasecal.plan/1", "frames": ' + frames + b"}}"


def test_json_body_over_the_json_limit_is_413_before_it_is_read(client: TestClient) -> None:
    """The upload limit (512 MiB) no longer applies to JSON: 4 MiB does, by Content-Length."""
    body = json.dumps({"name": "x" * DEFAULT_MAX_JSON_BYTES}).encode()
    detail = _problem(client.post("/sessions", content=body, headers=JSON), 413)["detail"]
    assert str(DEFAULT_MAX_JSON_BYTES) in detail and "PHASECAL_MAX_JSON_BYTES" in detail


def test_chunked_json_over_the_limit_is_413_while_streaming(client: TestClient) -> None:
    before = len(client.get("/sessions").json())

    def pieces():
        yield b'{"preset": "fast", "name": "'
        for _ in range(80):
            yield b"a" * 65536
        yield b'"}'

    r = client.post("/sessions", content=pieces(), headers=JSON)
    assert "content-length" not in r.request.headers
    assert "PHASECAL_MAX_JSON_BYTES" in _problem(r, 413)["detail"]
    assert len(client.get("/sessions").json()) == before


@pytest.mark.parametrize(("shape", "body", "status", "words"), [
    ("empty objects", _plan_body(b"[" + b"{}," * 1_300_000 + b"{}]"), 413, "values"),
    ("numbers", _plan_body(b"[" + b"0," * 2_000_000 + b"0]"), 413, "values"),
    ("many keys", b'{"plan": {' + b",".join(b'"k%07d":0' % i for i in range(300_000))
     + b"}}", 413, "values"),
    ("empty arrays", _plan_body(b"[" + b"[]," * 100_000 + b"[]]"), 413, "arrays/objects"),
    ("deep nesting", _plan_body(b"[" * 100_000 + b"]" * 100_000), 422, "levels deep"),
    ("UTF-16", '{"preset": "fast"}'.encode("utf-16"), 422, "UTF-8"),
])
def test_bodies_that_would_amplify_are_refused_before_parsing(
        client: TestClient, shape: str, body: bytes, status: int, words: str) -> None:
    """Under the byte limit, but each would need 10-25x its size as Python objects."""
    assert len(body) <= DEFAULT_MAX_JSON_BYTES, shape
    detail = _problem(client.post("/sessions", content=body, headers=JSON), status)["detail"]
    assert words in detail, detail


def test_point_routes_take_rows_of_numbers(client: TestClient) -> None:
    """Their larger budget is for numbers: rows of objects or strings would cost several
    times as much memory, and 200,000 bad rows answer one error, not 200,000."""
    path = f"{UNKNOWN_CAL}/project"
    objects = b'{"points": [' + b",".join(b'{"%040d": 0.5}' % i for i in range(1000)) + b"]}"
    assert "objects" in _problem(client.post(path, content=objects, headers=JSON),
                                 422)["detail"]
    strings = json.dumps({"points": [["a" * 40, "b", "c"]] * 1000})
    assert "strings" in _problem(client.post(path, content=strings, headers=JSON),
                                 422)["detail"]
    bad_rows = json.dumps({"points": [[False, 0, 1]] * MAX_POINTS})
    body = _problem(client.post(path, content=bad_rows, headers=JSON), 422)
    assert len(body["errors"]) == 1 and body["errors"][0]["loc"][:3] == ["body", "points", "0"]


def test_a_refused_body_leaves_no_idempotent_answer(client: TestClient) -> None:
    """Refused while the idempotency layer spools it: the key stays free for the retry."""
    big = _plan_body(b"[" + b"{}," * 1_300_000 + b"{}]")
    r = client.post("/sessions", content=big, headers={**JSON, "Idempotency-Key": "limits-1"})
    _problem(r, 413)
    r = client.post("/sessions", json={"preset": "fast"}, headers={"Idempotency-Key": "limits-1"})
    assert r.status_code == 201, r.text
    assert "idempotent-replayed" not in r.headers


def test_brackets_and_quotes_inside_strings_are_text(client: TestClient) -> None:
    """A string full of brackets, separators and escaped quotes nests nothing."""
    plan = dict(PLAN.to_dict(), note='[{,:\\"' * (MAX_TREE_STRING // 7))
    r = client.post("/sessions", json={"name": '"[[[', "plan": plan})
    assert r.status_code == 201, r.text


def test_largest_legitimate_bodies_pass(client: TestClient) -> None:
    """The largest preset plan, an extreme full-control plan and MAX_POINTS points."""
    largest = max((build_plan(15360, 8640, [0.1, 0.1], preset=p) for p in PRESETS),
                  key=lambda plan: len(plan.frames))
    extreme = build_plan(15360, 8640, [0.1, 0.1], steps=64, finest_period_px=4.0,
                         max_ratio=2.0)
    for plan in (largest, extreme):
        body = json.dumps({"name": "big", "plan": plan.to_dict()}, indent=2)
        r = client.post("/sessions", content=body, headers=JSON)
        assert r.status_code == 201, r.text
        assert r.json()["frame_count"] == len(plan.frames)
    row = [-123.45678901234568, 98.765432109876543, 1234.5678901234568]
    points = json.dumps({"points": [row] * MAX_POINTS}, indent=2).encode()
    assert len(points) > DEFAULT_MAX_JSON_BYTES  # the point routes have their own budget
    # an unknown calibration is a 404 from the route: the body passed every limit and check
    r = client.post(f"{UNKNOWN_CAL}/project", content=points, headers=JSON)
    assert r.status_code == 404, r.text
    too_many = json.dumps({"points": [row] * (MAX_POINTS + 1)})
    assert "points" in _problem(client.post(f"{UNKNOWN_CAL}/project", content=too_many,
                                            headers=JSON), 422)["detail"]


def test_uploads_keep_the_upload_limit(tmp_path: Path) -> None:
    limit = 16384  # room for the test plan (5 KB), not for the maps (600 KB)
    cfg = ServiceConfig(data_dir=tmp_path / "data", executor="threads", max_json_bytes=limit)
    with TestClient(create_app(cfg), raise_server_exceptions=False) as c:
        sid = c.post("/sessions", json={"plan": PLAN.to_dict()}).json()["id"]
        data = good_maps(1, size=(160, 120)).to_npz_bytes()
        assert len(data) > limit
        r = c.post(f"/sessions/{sid}/poses/import-maps", files={"file": ("m.npz", data)})
        assert r.status_code == 201, r.text
        # the same multipart body on a route that takes no files is held to the JSON limit
        r = c.post("/sessions", files={"file": ("m.npz", data)})
        assert f"{limit} bytes" in _problem(r, 413)["detail"]
        # and so is a form that is not multipart, even on an upload route
        r = c.post(f"/sessions/{sid}/poses/import", content=b"a=&" * limit,
                   headers={"content-type": "application/x-www-form-urlencoded"})
        _problem(r, 413)


def test_the_json_limit_setting(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("PHASECAL_MAX_JSON_BYTES", "12345")
    assert ServiceConfig.from_env().max_json_bytes == 12345
    monkeypatch.setenv("PHASECAL_MAX_JSON_BYTES", "4MiB")
    with pytest.raises(ValueError, match="PHASECAL_MAX_JSON_BYTES"):
        ServiceConfig.from_env()
    # raising it admits a larger body; the upload limit still bounds every body
    big = json.dumps({"preset": "fast", "name": "n" * 5_000_000}).encode()
    cfg = ServiceConfig(data_dir=tmp_path / "a", executor="threads", max_json_bytes=8 << 20)
    with TestClient(create_app(cfg), raise_server_exceptions=False) as c:
        assert "name" in _problem(c.post("/sessions", content=big, headers=JSON), 422)["detail"]
    cfg = ServiceConfig(data_dir=tmp_path / "b", executor="threads", max_upload_bytes=10_000)
    with TestClient(create_app(cfg), raise_server_exceptions=False) as c:
        r = c.post("/sessions", content=big[:20_000] + b'"}', headers=JSON)
        assert "10000 bytes" in _problem(r, 413)["detail"]
        assert "PHASECAL_MAX_UPLOAD_BYTES" in r.json()["detail"]


def test_schemas_bound_plans_configs_and_ids(client: TestClient) -> None:
    plan = PLAN.to_dict()
    cases = [
        ("/sessions", {"plan": dict(plan, frames=[{}] * (MAX_PLAN_FRAMES + 1))}, "frames"),
        ("/sessions", {"plan": dict(plan, frames=[{f"k{i}": 0 for i in
                                                   range(MAX_FRAME_KEYS + 1)}])}, "frames[0]"),
        ("/sessions", {"plan": dict(plan, meta=[[[[[[[[[0]]]]]]]]])}, "levels"),
        ("/sessions", {"plan": dict(plan, note="x" * (MAX_TREE_STRING + 1))}, "characters"),
        ("/sessions", {"preset": "p" * 33}, "preset"),
        ("/sessions", {"preset": "fast", "rig_id": "r" * (MAX_ID_LENGTH + 1)}, "rig_id"),
        ("/rigs", {"name": "r", "config": {f"k{i}": 0 for i in
                                           range(MAX_RIG_CONFIG_KEYS + 1)}}, "config"),
        ("/rigs", {"name": "r", "config": {"a": {"b": [[[[[[[[0]]]]]]]]}}}, "levels"),
    ]
    for path, body, words in cases:
        detail = _problem(client.post(path, json=body), 422)["detail"]
        assert words in detail, (body, detail)
    sid = client.post("/sessions", json={"preset": "fast"}).json()["id"]
    r = client.post(f"/sessions/{sid}/calibrations",
                    json={"model": "sgcc", "pose_ids": ["p" * (MAX_ID_LENGTH + 1)]})
    assert "pose_ids" in _problem(r, 422)["detail"]
    assert MAX_TREE_DEPTH == 8  # the nesting cases above are one level past it


def test_openapi_shows_the_bounds(client: TestClient) -> None:
    schemas = client.get("/openapi.json").json()["components"]["schemas"]
    plan = next(s for s in schemas["SessionCreate"]["properties"]["plan"]["anyOf"]
                if s.get("type") == "object")
    frames = plan["properties"]["frames"]
    assert frames["items"]["maxProperties"] == MAX_FRAME_KEYS
    assert str(MAX_PLAN_FRAMES) in frames["description"]
    assert schemas["RigCreate"]["properties"]["config"]["maxProperties"] == MAX_RIG_CONFIG_KEYS
    assert schemas["SessionCreate"]["properties"]["preset"]["anyOf"][0]["maxLength"] == 32


def test_upload_and_point_routes_are_the_apps(client: TestClient) -> None:
    """The budgets are chosen by path: they must name exactly the routes that take files
    (multipart request bodies in the OpenAPI document), and routes that exist."""
    paths = client.get("/openapi.json").json()["paths"]
    takes_files = {path for path, ops in paths.items() for op in ops.values()
                   if "multipart/form-data" in op.get("requestBody", {}).get("content", {})}
    assert takes_files == set(UPLOAD_ROUTES)
    assert {path for path in POINT_ROUTES if "post" in paths.get(path, {})} == set(POINT_ROUTES)


@pytest.mark.slow
def test_server_memory_stays_bounded_for_50_mb_bodies(tmp_path: Path) -> None:
    """In a real `phasecal serve` process: 50 MB bodies of every shape (declared and
    chunked) and bodies just under the JSON limit are refused with at most 100 MB of RSS
    growth (it was 1.3 GB for 50 MB of `[{},...]`); the largest valid ones still pass."""
    proc, url = start_serve(tmp_path / "data", executor="threads")
    try:
        rows = run_body_cases(url, proc.pid, body_cases() + legitimate_cases())
    finally:
        proc.terminate()
        proc.wait(30)
    for row in rows:
        assert row["status"] in row["expected"], row
        if row["attack"]:
            assert row["rss_growth_mb"] <= MAX_GROWTH_MB, row
            assert row["seconds"] < 20, row  # refused early; bound for a loaded 2-core machine
