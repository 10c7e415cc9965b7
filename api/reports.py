"""Calibration reports and model diffs built from the stored files, cached next to them.

The report of a calibration is drawn on first request from `model.json`, `result.json`,
the session's `plan.json` and its poses' `maps.npz` into `calibrations/<id>/report/`
(written in a scratch folder and moved into place), so it is reproducible from stored data
and costs nothing the second time.
"""

from __future__ import annotations

import json
import threading
from pathlib import Path
from typing import Any

import numpy as np
from sqlalchemy import select

from api.db import CalibrationRecord
from api.problems import Problem
from api.services import Services
from api.store import check_id
from calibration import gather, load_model, write_diff, write_report
from calibration.shared.maps import load_maps
from calibration.shared.plan import read_plan

REPORT_DIR = "report"
_locks: dict[str, threading.Lock] = {}
_locks_guard = threading.Lock()


def _lock(key: str) -> threading.Lock:
    with _locks_guard:
        return _locks.setdefault(key, threading.Lock())


def succeeded(svc: Services, cal_id: str) -> CalibrationRecord:
    """The calibration record, 404 if unknown, 409 unless it succeeded."""
    check_id(cal_id, "cal", "calibration")
    with svc.db.session() as s:
        rec = s.get(CalibrationRecord, cal_id)
        if rec is None:
            raise Problem(404, "not-found", f"calibration {cal_id!r} does not exist")
    if rec.status != "succeeded":
        raise Problem(409, "not-ready", f"calibration {cal_id} is {rec.status}; its report "
                      "exists once it succeeded")
    return rec


def _maps(svc: Services, pose_ids: list[str]) -> list[Any]:
    out = []
    for pid in pose_ids:
        path = svc.store.file(pid, "maps.npz")
        if not path.is_file():
            raise Problem(409, "not-ready", f"pose {pid}: maps.npz is missing from the data "
                          "directory; the report cannot be recomputed")
        out.append(load_maps(path))
    return out


def report_dir(svc: Services, cal_id: str) -> Path:
    """The folder holding report.html and its PNGs, drawn now if not cached."""
    rec = succeeded(svc, cal_id)
    final = svc.store.dir_for(cal_id) / REPORT_DIR
    with _lock(cal_id):
        if (final / "report.html").is_file():
            return final

        cal_dir = svc.store.dir_for(cal_id)
        model = load_model(cal_dir / "model.json")
        result = json.loads((cal_dir / "result.json").read_text())
        plan = read_plan(svc.store.dir_for(rec.session_id) / "plan.json")
        labels = [*rec.pose_ids, *rec.heldout_pose_ids]
        data = gather(model, result, _maps(svc, rec.pose_ids), _maps(svc, rec.heldout_pose_ids),
                      plan.screen, labels=labels)
        links = [(f"difference to {o} ({m})", f"/calibrations/{cal_id}/diff/{o}/diff.png")
                 for o, m in _siblings(svc, rec)]
        tmp = svc.store.temp_dir()
        write_report(data, tmp, f"Calibration {cal_id} ({rec.model}) of session "
                     f"{rec.session_id}", links)
        svc.store.replace_dir(tmp, final)
    return final


def _siblings(svc: Services, rec: CalibrationRecord) -> list[tuple[str, str]]:
    """Other succeeded calibrations of the same session (id, model), for diff links."""
    with svc.db.session() as s:
        rows = s.execute(select(CalibrationRecord.id, CalibrationRecord.model).where(
            CalibrationRecord.session_id == rec.session_id,
            CalibrationRecord.status == "succeeded", CalibrationRecord.id != rec.id)).all()
    return [(r[0], r[1]) for r in rows]


def _covered_pixels(masks: list[np.ndarray], step: int) -> np.ndarray:
    """Grid pixels (N, 2) seen by at least one pose: models are compared where data exist."""
    union = np.any(masks, axis=0)[::step, ::step]
    v, u = np.nonzero(union)
    return np.stack([u * step, v * step], axis=1).astype(np.float64)


def diff_dir(svc: Services, cal_a: str, cal_b: str) -> Path:
    """Folder with diff.json and diff.png comparing two calibrations (drawn once, cached)."""
    a, b = succeeded(svc, cal_a), succeeded(svc, cal_b)
    if cal_a == cal_b:
        raise Problem(422, "validation-error", "diff: compare two different calibrations")
    final = svc.store.dir_for(cal_a) / f"diff-{cal_b}"
    with _lock(f"{cal_a}/{cal_b}"):
        if (final / "diff.json").is_file():
            return final

        ma = load_model(svc.store.file(cal_a, "model.json"))
        mb = load_model(svc.store.file(cal_b, "model.json"))
        if ma.image_size != mb.image_size:
            raise Problem(422, "validation-error", f"diff: {cal_a} is {ma.image_size[0]}x"
                          f"{ma.image_size[1]} px but {cal_b} is {mb.image_size[0]}x"
                          f"{mb.image_size[1]} px")
        masks = [m.mask for m in _maps(svc, sorted(set(a.pose_ids) & set(b.pose_ids))
                                       or a.pose_ids)]
        tmp = svc.store.temp_dir()
        try:
            write_diff(ma, mb, tmp, _covered_pixels(masks, 4), 4.0,
                       (f"{cal_a} ({a.model})", f"{cal_b} ({b.model})"))
        except ValueError as exc:
            raise Problem(422, "validation-error", str(exc)) from None
        svc.store.replace_dir(tmp, final)
    return final
