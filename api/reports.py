"""Calibration reports and model diffs built from the stored files, cached next to them.

A calibration job (one model or a batch) draws its reports as its last step (`draw_in_job`),
on the executor, so the first open of a report is a file read. A calibration without one
(calibrated before reports were drawn by jobs, of an older layout, or whose drawing failed)
gets it drawn in the background on its first request (`ready_report`), which answers at
once; until it is in place the page says so and reloads itself. Each report is written in a
scratch folder and moved into `calibrations/<id>/report/`, so it is reproducible from
stored data and costs nothing the second time.
"""

from __future__ import annotations

import json
import logging
import shutil
import threading
import time
from concurrent.futures import Future
from pathlib import Path
from typing import TYPE_CHECKING, Any

from sqlalchemy import select

from api.db import CalibrationRecord, RigRecord, SessionRecord
from api.problems import Problem
from api.store import check_id
from api.version import phasecal_version
from calibration import (
    DiffInputs,
    FitFiles,
    ReportHeader,
    ReportInputs,
    draw_diff,
    draw_report,
    is_current,
    load_model,
    served_downloads,
)

if TYPE_CHECKING:
    from api.services import Services

REPORT_DIR = "report"
REFRESH_S = 2
log = logging.getLogger("phasecal.reports")
_locks: dict[str, threading.RLock] = {}
_locks_guard = threading.Lock()
_drawing: dict[str, Future] = {}  # cal id -> background drawing in flight
_failed: dict[str, str] = {}  # cal id -> why its last background drawing failed


def _lock(key: str) -> threading.RLock:
    """One lock per report or diff (re-entrant: a drawing that ends before its callback is
    attached places itself in the thread that started it)."""
    with _locks_guard:
        return _locks.setdefault(key, threading.RLock())


def calibration(svc: Services, cal_id: str) -> CalibrationRecord:
    """The calibration record (404 if unknown)."""
    check_id(cal_id, "cal", "calibration")
    with svc.db.session() as s:
        rec = s.get(CalibrationRecord, cal_id)
        if rec is None:
            raise Problem(404, "not-found", f"calibration {cal_id!r} does not exist")
    return rec


def succeeded(svc: Services, cal_id: str) -> CalibrationRecord:
    """The calibration record, 404 if unknown, 409 unless it succeeded."""
    rec = calibration(svc, cal_id)
    if rec.status != "succeeded":
        raise Problem(409, "not-ready", f"calibration {cal_id} is {rec.status}; its report "
                      "exists once it succeeded")
    return rec


def _maps(svc: Services, pose_ids: list[str]) -> list[str]:
    out = []
    for pid in pose_ids:
        path = svc.store.file(pid, "maps.npz")
        if not path.is_file():
            raise Problem(409, "not-ready", f"pose {pid}: maps.npz is missing from the data "
                          "directory; the report cannot be recomputed")
        out.append(str(path))
    return out


def _cameras(config: dict[str, Any]) -> str:
    """The rig's cameras in words, from its stored config."""
    named = config.get("cameras")
    if isinstance(named, list):
        return ", ".join(f"{c.get('name', '?')} ({c.get('backend', 'simulated')})"
                         for c in named)
    cam = config.get("camera") or {}
    return f"one camera ({cam.get('backend', 'simulated')})"


def _header(svc: Services, rec: CalibrationRecord) -> ReportHeader:
    with svc.db.session() as s:
        ses = s.get(SessionRecord, rec.session_id)
        rig = s.get(RigRecord, ses.rig_id) if ses is not None and ses.rig_id else None
    session = f"{ses.name or 'unnamed'} ({rec.session_id})" if ses is not None else rec.session_id
    rig_text = f"{rig.name} ({rig.id}, {rig.config.get('kind', 'simulated')})" if rig else "none"
    return ReportHeader(
        title=f"Calibration {rec.id} ({rec.model})", session=session, rig=rig_text,
        cameras=_cameras(rig.config) if rig else "not recorded",
        date=time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime(rec.created_at)),
        software=f"phasecal {phasecal_version()}", poses_used=list(rec.pose_ids),
        heldout=list(rec.heldout_pose_ids))


def _inputs(svc: Services, rec: CalibrationRecord) -> ReportInputs:
    cal_dir = svc.store.dir_for(rec.id)
    model = load_model(cal_dir / "model.json")
    return ReportInputs(
        model=str(cal_dir / "model.json"),
        plan=str(svc.store.dir_for(rec.session_id) / "plan.json"),
        maps=_maps(svc, rec.pose_ids), heldout_maps=_maps(svc, rec.heldout_pose_ids),
        result=str(cal_dir / "result.json"), labels=[*rec.pose_ids, *rec.heldout_pose_ids],
        header=_header(svc, rec), downloads=served_downloads(model, rec.id), links=None)


def draw_in_job(svc: Services, cal_ids: list[str]) -> None:
    """Draw just-fitted calibrations' reports on the executor, all at once, and wait for
    them (a calibration job's last step). A report that cannot be drawn does not fail its
    calibration: it is logged, and the first request tries again."""
    started = []
    for cal_id in cal_ids:
        tmp = svc.store.temp_dir()
        try:
            inputs = _inputs(svc, calibration(svc, cal_id))
            started.append((cal_id, tmp, svc.executor.submit(draw_report, inputs, str(tmp))))
        # Whatever went wrong, the fit stands; the report is drawn again on its first request.
        except Exception as exc:
            _not_drawn(cal_id, tmp, exc)
    for cal_id, tmp, future in started:
        try:
            future.result()
        except Exception as exc:
            _not_drawn(cal_id, tmp, exc)
            continue
        with _lock(cal_id):
            svc.store.replace_dir(tmp, svc.store.dir_for(cal_id) / REPORT_DIR)


def _not_drawn(cal_id: str, tmp: Path, exc: Exception) -> None:
    log.warning("calibration %s: report not drawn: %s", cal_id, exc)
    shutil.rmtree(tmp, ignore_errors=True)


def ready_report(svc: Services, cal_id: str) -> Path | None:
    """The folder holding report.html and its PNGs, or None while it is being drawn (the
    calibration still running, or its report drawing in the background, started here)."""
    rec = calibration(svc, cal_id)
    if rec.status in ("queued", "running"):
        return None
    if rec.status != "succeeded":
        raise Problem(409, "not-ready", f"calibration {cal_id} is {rec.status}; a report "
                      "exists only for a calibration that succeeded")
    final = svc.store.dir_for(cal_id) / REPORT_DIR
    with _lock(cal_id):
        if _current(final / "report.html"):
            return final
        if cal_id in _failed:
            reason = _failed.pop(cal_id)  # the next request tries again
            raise Problem(500, "report-failed", f"calibration {cal_id}: drawing its report "
                          f"failed: {reason}")
        if cal_id not in _drawing:
            inputs = _inputs(svc, rec)
            tmp = svc.store.temp_dir()
            future = svc.executor.submit(draw_report, inputs, str(tmp))
            _drawing[cal_id] = future
            future.add_done_callback(lambda f: _placed(svc, cal_id, f, tmp, final))
    return None


def _current(page: Path) -> bool:
    """A stored report page of the current layout (older ones are drawn again)."""
    try:
        with page.open(encoding="utf-8") as fh:
            return is_current(fh.read(4096))
    except FileNotFoundError:
        return False


def _placed(svc: Services, cal_id: str, future: Future, tmp: Path, final: Path) -> None:
    """Move a background drawing into place (or remember why it failed)."""
    with _lock(cal_id):
        _drawing.pop(cal_id, None)
        exc = future.exception()
        if exc is None:
            svc.store.replace_dir(tmp, final)
        else:
            shutil.rmtree(tmp, ignore_errors=True)
            _failed[cal_id] = str(exc) or type(exc).__name__


def drawing_page(cal_id: str, status: str) -> str:
    """What a report request shows until the report is in place: never a blank tab."""
    what = ("the calibration is still running; its report is drawn as its last step"
            if status in ("queued", "running") else "its report is being drawn")
    return (f"<!doctype html><html lang='en'><head><meta charset='utf-8'>"
            f"<meta http-equiv='refresh' content='{REFRESH_S}'>"
            f"<title>Calibration {cal_id}: report being drawn</title></head>"
            f"<body style='font-family:system-ui,sans-serif;margin:2em'>"
            f"<h1>Calibration {cal_id}</h1><p id='drawing'>The report is not ready yet: {what}. "
            f"This page reloads itself every {REFRESH_S} s.</p></body></html>")


def compare_links(svc: Services, cal_id: str) -> list[tuple[str, str]]:
    """(text, URL) of the difference pages to the other succeeded calibrations of the
    calibration's session, as they are now."""
    rec = calibration(svc, cal_id)
    return [(f"difference to {o} ({m})", f"/calibrations/{cal_id}/diff/{o}/diff.html")
            for o, m in _siblings(svc, rec)]


def _siblings(svc: Services, rec: CalibrationRecord) -> list[tuple[str, str]]:
    """Other succeeded calibrations of the same session (id, model), for diff links."""
    with svc.db.session() as s:
        rows = s.execute(select(CalibrationRecord.id, CalibrationRecord.model).where(
            CalibrationRecord.session_id == rec.session_id,
            CalibrationRecord.status == "succeeded", CalibrationRecord.id != rec.id)).all()
    return [(r[0], r[1]) for r in rows]


def _fit_files(svc: Services, rec: CalibrationRecord) -> FitFiles:
    return FitFiles(str(svc.store.file(rec.id, "result.json")),
                    str(svc.store.dir_for(rec.session_id) / "plan.json"),
                    _maps(svc, rec.pose_ids))


def diff_dir(svc: Services, cal_a: str, cal_b: str) -> Path:
    """Folder with diff.html, its images and diff.json comparing two calibrations against
    their combined uncertainty (drawn once on the executor, cached)."""
    a, b = succeeded(svc, cal_a), succeeded(svc, cal_b)
    if cal_a == cal_b:
        raise Problem(422, "validation-error", "diff: compare two different calibrations")
    final = svc.store.dir_for(cal_a) / f"diff-{cal_b}"
    with _lock(f"{cal_a}/{cal_b}"):
        if (final / "diff.html").is_file():
            return final

        ma = load_model(svc.store.file(cal_a, "model.json"))
        mb = load_model(svc.store.file(cal_b, "model.json"))
        if ma.image_size != mb.image_size:
            raise Problem(422, "validation-error", f"diff: {cal_a} is {ma.image_size[0]}x"
                          f"{ma.image_size[1]} px but {cal_b} is {mb.image_size[0]}x"
                          f"{mb.image_size[1]} px")
        tmp = svc.store.temp_dir()
        inputs = DiffInputs(
            str(svc.store.file(cal_a, "model.json")), str(svc.store.file(cal_b, "model.json")),
            (f"{cal_a} ({a.model})", f"{cal_b} ({b.model})"), str(tmp),
            _maps(svc, sorted(set(a.pose_ids) & set(b.pose_ids)) or a.pose_ids), 4.0,
            (_fit_files(svc, a), _fit_files(svc, b)))
        try:
            svc.executor.submit(draw_diff, inputs).result()
        except ValueError as exc:
            raise Problem(422, "validation-error", str(exc)) from None
        svc.store.replace_dir(tmp, final)
    return final


def diff_summary(folder: Path) -> dict[str, Any]:
    """diff.json of a drawn difference."""
    return json.loads((folder / "diff.json").read_text())
