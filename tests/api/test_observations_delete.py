"""Deleting from target sessions over REST: a view, a calibration and a whole session go with
their files; what does not exist is a 404 naming it; another session is untouched."""

from __future__ import annotations

import pytest
from fastapi.testclient import TestClient

from api.app import create_app
from api.config import ServiceConfig
from tests.calibration.targets.conftest import SAMPLE_SPEC, sample_images


@pytest.fixture
def served(tmp_path):
    data = tmp_path / "data"
    app = create_app(ServiceConfig(data_dir=data, executor="threads", max_upload_bytes=1 << 20))
    with TestClient(app) as c:
        yield c, data


def _session_with_views(client, count: int) -> tuple[str, list[str]]:
    sid = client.post("/target-sessions", json={"target": SAMPLE_SPEC}).json()["id"]
    for img in sample_images("left")[:count]:
        r = client.post(f"/target-sessions/{sid}/views",
                        files={"file": (img.name, img.read_bytes())})
        assert r.status_code == 201, r.text
    return sid, [v["id"] for v in client.get(f"/target-sessions/{sid}/views").json()]


def test_views_calibrations_and_sessions_are_deleted_with_their_files(served):
    client, data = served
    sid, views = _session_with_views(client, 5)
    other, other_views = _session_with_views(client, 1)
    cal = client.post(f"/target-sessions/{sid}/calibrations", json={"model": "opencv5"})
    assert cal.status_code == 201, cal.text
    cid = cal.json()["id"]
    assert any(data.rglob(f"{views[0]}.npz")) and any(p.is_dir() for p in data.rglob(cid))

    assert client.delete(f"/target-sessions/{sid}/views/{views[0]}").status_code == 204
    assert not any(data.rglob(f"{views[0]}.npz"))
    assert [v["id"] for v in client.get(f"/target-sessions/{sid}/views").json()] == views[1:]
    r = client.delete(f"/target-sessions/{sid}/views/{views[0]}")
    assert r.status_code == 404 and views[0] in r.json()["detail"]
    r = client.delete(f"/target-sessions/{sid}/views/{other_views[0]}")  # not this session's
    assert r.status_code == 404

    assert client.delete(f"/target-sessions/{sid}/calibrations/{cid}").status_code == 204
    assert client.get(f"/target-sessions/{sid}/calibrations/{cid}").status_code == 404
    assert not any(data.rglob(cid))

    assert client.delete(f"/target-sessions/{sid}").status_code == 204
    assert client.get(f"/target-sessions/{sid}").status_code == 404
    assert not any(data.rglob(f"{views[1]}.npz")) and not any(data.rglob(sid))
    assert client.delete(f"/target-sessions/{sid}").status_code == 404
    assert client.get(f"/target-sessions/{other}").json()["views"] == 1  # untouched
    assert client.delete("/target-sessions/not-an-id").status_code in (404, 422)
