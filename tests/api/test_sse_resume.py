"""SSE job events carry ids; a client reconnecting with Last-Event-ID resumes after it."""

from __future__ import annotations

import json
import time
from collections.abc import Iterator
from pathlib import Path

import httpx

from api.client import PhasecalClient
from api.config import ServiceConfig
from api.inprocess import running_service
from api.stream_limits import EVENTS, stream_limiter
from tests.api.test_api_session import small_rig


def _events(lines: Iterator[str], limit: int | None = None) -> list[tuple[str, str, dict]]:
    """(id, event, data) of each event until `end` or `limit` events, read from `lines`
    (a response's `iter_lines()`, which the caller holds: once the last reference to that
    iterator goes, httpx closes the connection, which the server sees as a hang-up)."""
    out, ev, eid = [], {}, ""
    for line in lines:
        if line.startswith("id: "):
            eid = line[4:]
        elif line.startswith("event: "):
            ev["name"] = line[7:]
        elif line.startswith("data: "):
            out.append((eid, ev.pop("name", "message"), json.loads(line[6:])))
            if out[-1][1] == "end" or (limit and len(out) >= limit):
                break
    return out


def test_sse_ids_and_resume_from_last_event_id(tmp_path: Path) -> None:
    with running_service(ServiceConfig(data_dir=tmp_path / "data")) as (url, _):
        client = PhasecalClient(url)
        rig = client.post("/rigs", {"name": "slow", "config": small_rig(slow=True)})
        # (74 frames on the slow rig: the job outlives the hang-up by seconds, where the 38 of
        # "fast" took ~1.5 s and could end first on a quick machine)
        ses = client.post("/sessions", {"name": "sse", "rig_id": rig["id"],
                                        "preset": "precise"})
        job = client.post(f"/sessions/{ses['id']}/poses", {})
        path = f"{url}/jobs/{job['id']}/events"
        with httpx.stream("GET", path, timeout=120) as r:
            first = _events(r.iter_lines(), limit=3)
        ids = [int(e[0]) for e in first]
        assert ids == sorted(ids) and len(set(ids)) == len(ids), first
        last = ids[-1]
        with httpx.stream("GET", path, timeout=300, headers={"Last-Event-ID": str(last)}) as r:
            rest = _events(r.iter_lines())
        assert rest[-1][:2] == ("end", "end") and rest[-1][2]["status"] == "succeeded"
        numeric = [int(e[0]) for e in rest[:-1]]
        assert all(i > last for i in numeric), (last, numeric)  # nothing replayed
        assert numeric == sorted(numeric)
        # Once the job is over, a reconnect gets just the final state.
        with httpx.stream("GET", path, timeout=30, headers={"Last-Event-ID": str(last)}) as r:
            assert [e[:2] for e in _events(r.iter_lines())] == [("end", "end")]
        client.close()


def test_sse_client_that_hangs_up_frees_its_stream_slot(tmp_path: Path) -> None:
    with running_service(ServiceConfig(data_dir=tmp_path / "data", executor="threads")) as (
            url, app):
        limiter = stream_limiter(app, EVENTS)
        client = PhasecalClient(url)
        # 74 frames rendered at 8x8 samples a pixel (~0.1 s or more each): the job outlives
        # the hang-up by several seconds even on a quick, idle machine (the slow rig's 4x4
        # once finished before its first event on one)
        config = small_rig(slow=True)
        config["camera"]["supersample"] = 8
        rig = client.post("/rigs", {"name": "slow", "config": config})
        ses = client.post("/sessions", {"name": "sse", "rig_id": rig["id"],
                                        "preset": "precise"})
        job = client.post(f"/sessions/{ses['id']}/poses", {})
        with httpx.stream("GET", f"{url}/jobs/{job['id']}/events", timeout=120) as r:
            lines = r.iter_lines()  # held open: the client hangs up only when the block ends
            first = _events(lines, limit=1)
            assert first and first[0][1] == "progress", first
            assert limiter.active() == 1
        deadline = time.monotonic() + 5  # released at the hang-up, not at the job's end
        while limiter.active() and time.monotonic() < deadline:
            time.sleep(0.05)
        assert limiter.active() == 0
        assert client.get(f"/jobs/{job['id']}")["status"] in ("queued", "running")
        assert client.wait(job, timeout_s=300)["status"] == "succeeded"
        client.close()
