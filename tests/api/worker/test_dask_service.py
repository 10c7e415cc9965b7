"""The REST service with its executor on a real LocalCluster gives the same results as the
in-process executor: a pose decoded through `/sessions/.../poses/import` and, once the
calibration fit exists, a batch of calibrations through `/batches/calibrations`."""

from __future__ import annotations

import io
import math
import time
from pathlib import Path

import dask
import numpy as np
import pytest
from fastapi.testclient import TestClient

from acquisition.patterns import build_plan
from api.app import create_app
from api.config import ServiceConfig
from api.worker.dask_executor import DaskExecutor, start_local_cluster
from calibration.shared.maps import load_maps
from calibration.shared.plan import CosineFrame, FlatFrame, Plan
from tests.api.worker.test_dask_batch import FIT_AGREE_PX, model_disagreement_px

H, W = 96, 128
TERMINAL = ("succeeded", "failed", "cancelled", "interrupted")


def render(plan: Plan, seed: int) -> np.ndarray:
    """(F, H, W) uint8 frames of `plan` seen through an affine test camera, with noise."""
    v, u = np.mgrid[0:H, 0:W].astype(np.float64)
    x, y = 20.0 + 1.3 * u + 0.04 * v, 15.0 + 1.2 * v - 0.02 * u
    rng = np.random.default_rng(seed)
    frames = []
    for f in plan.frames:
        if isinstance(f, FlatFrame):
            lin = np.full((H, W), f.level)
        else:
            assert isinstance(f, CosineFrame)
            c = x if f.axis == "x" else y
            lin = f.offset + f.amplitude * np.cos(2 * math.pi * c / f.period_px + f.phase_shift)
        img = 15.0 + 220.0 * lin + rng.normal(0.0, 1.0, (H, W))
        frames.append(np.clip(np.rint(img), 0, 255).astype(np.uint8))
    return np.stack(frames)


@pytest.fixture(scope="module")
def cluster():
    # Workers keep this process's BLAS threading (Dask would pin it to 1 thread), so both
    # executors run the same floating-point code path and can be compared bit for bit.
    env = {k: v for k, v in dask.config.get("distributed.nanny.pre-spawn-environ").items()
           if not k.endswith("_NUM_THREADS")}
    with dask.config.set({"distributed.scheduler.allowed-failures": 1,
                          "distributed.nanny.pre-spawn-environ": env}):
        lc = start_local_cluster(2)
    yield lc
    lc.close()


@pytest.fixture(scope="module")
def plan() -> Plan:
    return build_plan(256, 192, 0.5, preset="fast")


def _wait(c: TestClient, job: dict) -> dict:
    while True:
        state = c.get(f"/jobs/{job['id']}").json()
        if state["status"] in TERMINAL:
            return state
        time.sleep(0.05)


def _decode_via_service(data_dir: Path, executor: str | None, plan: Plan,
                        frames: np.ndarray) -> tuple[dict, bytes]:
    app = create_app(ServiceConfig(data_dir=data_dir, executor=executor))
    buf = io.BytesIO()
    np.save(buf, frames)
    with TestClient(app) as c:
        if executor is not None:
            assert isinstance(app.state.services.executor, DaskExecutor)
        ses = c.post("/sessions", json={"name": "dask", "plan": plan.to_dict()}).json()
        job = c.post(f"/sessions/{ses['id']}/poses/import",
                     files=[("files", ("frames.npy", buf.getvalue(), "application/octet-stream"))]
                     ).json()
        final = _wait(c, job)
        assert final["status"] == "succeeded", final
        assert final["done"] == final["total"] > 0
        return final, c.get(f"{final['resource']}/maps.npz").content


def test_decode_job_on_cluster_matches_in_process(cluster, plan, tmp_path):
    frames = render(plan, seed=5)
    _, local = _decode_via_service(tmp_path / "local", None, plan, frames)
    _, remote = _decode_via_service(tmp_path / "dask", cluster.scheduler_address, plan, frames)
    a, b = load_maps(local), load_maps(remote)
    assert a.valid_count() > 0.9 * H * W
    for key in ("x", "y", "sigma_x", "sigma_y", "mask", "modulation_x", "modulation_y"):
        assert np.array_equal(getattr(a, key), getattr(b, key), equal_nan=key != "mask"), key


def test_batch_endpoint_on_cluster_matches_in_process(cluster, tmp_path):
    from calibration.shared.maps import save_maps
    from hw_mocks.cameras import mild_pinhole
    from hw_mocks.poses import random_poses
    from hw_mocks.synthetic import synthetic_maps

    plan = build_plan(1920, 1080, 0.2745)
    camera = mild_pinhole(320, 240)
    rng = np.random.default_rng(11)
    maps_files = []
    for k, pose in enumerate(random_poses(camera, plan.screen, 4, rng)):
        m, _ = synthetic_maps(camera, pose, plan.screen, sigma_px=0.05, rng=rng)
        save_maps(m, tmp_path / f"pose{k}.npz")
        maps_files.append(tmp_path / f"pose{k}.npz")
    results = {}
    for label, executor in (("local", None), ("dask", cluster.scheduler_address)):
        app = create_app(ServiceConfig(data_dir=tmp_path / label, executor=executor))
        store = app.state.services.store
        with TestClient(app) as c:
            ses = c.post("/sessions", json={"name": label, "plan": plan.to_dict()}).json()
            for f in maps_files:
                r = c.post(f"/sessions/{ses['id']}/poses/import-maps",
                           files={"file": (f.name, f.read_bytes(), "application/octet-stream")})
                assert r.status_code == 201, r.text
            # in-process: one model per batch, because concurrent fits in threads of one
            # process share OpenCV's global thread setting (not repeatable: docs/calibration.md,
            # pipeline step 3)
            sweeps = ([["opencv5"], ["opencv-rational"]] if executor is None
                      else [["opencv5", "opencv-rational"]])
            for models in sweeps:
                r = c.post("/batches/calibrations", json={
                    "session_ids": [ses["id"]], "models": [{"model": m} for m in models]})
                assert r.status_code == 202, r.text
                final = _wait(c, r.json())
                assert final["status"] == "succeeded", final
            cals = c.get("/calibrations", params={"session_id": ses["id"]}).json()
            assert sorted(x["status"] for x in cals) == ["succeeded", "succeeded"]
            results[label] = {x["model"]: store.file(x["id"], "model.json") for x in cals}
    assert results["dask"].keys() == results["local"].keys()
    for model in results["local"]:
        assert model_disagreement_px(results["local"][model], results["dask"][model]) < \
            FIT_AGREE_PX, model
