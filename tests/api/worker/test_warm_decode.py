"""A live capture warms another worker's compiled decoder (`warm_decode_task`)."""

from __future__ import annotations

import sys

from api.worker.tasks import warm_decode_task


def test_warm_decode_task_loads_the_kernels_for_any_image_size() -> None:
    warm_decode_task(640 * 480)  # live decodes use the kernels at every size
    assert "calibration.decode.kernel_sums" in sys.modules
    assert "calibration.decode.accumulate_kernel" in sys.modules


def test_warm_decode_task_primes_the_sums_of_the_coming_decodes(tmp_path) -> None:
    """With the capture's plan and shape the warm task also allocates and keeps that decode's
    sums, so this worker's first pose reuses them (no first-touch faults during its capture)."""
    from acquisition.patterns import build_plan
    from calibration.decode import StreamingDecoder, sums_cache
    from calibration.shared.plan import write_plan

    plan = build_plan(1920, 1080, 0.2745)
    write_plan(plan, tmp_path / "plan.json")
    sums_cache.release()
    try:
        warm_decode_task(64 * 48, str(tmp_path / "plan.json"), (48, 64))
        assert sums_cache.kept_bytes() > 0
        kept = sums_cache.kept_arrays()[0]
        dec = StreamingDecoder(plan, (48, 64), compiled=True)  # as the live decode task
        dec.prepare()
        assert dec._acc.block is kept and not kept.any()
    finally:
        sums_cache.release()


def test_warm_decode_task_keeps_the_sums_a_worker_already_holds(tmp_path) -> None:
    """Every large capture submits a warm task: in a worker that already keeps a decode's
    sums it must not allocate or zero them again (each pose would pay ~1 GB of writes in the
    other worker while it captures)."""
    import numpy as np

    from acquisition.patterns import build_plan
    from calibration.decode import sums_cache
    from calibration.shared.plan import write_plan

    write_plan(build_plan(1920, 1080, 0.2745), tmp_path / "plan.json")
    held = np.full((3, 48 * 64), 7.0)
    sums_cache.keep([held])
    try:
        warm_decode_task(64 * 48, str(tmp_path / "plan.json"), (48, 64))
        assert sums_cache.kept_arrays() == [held] and (held == 7.0).all()
    finally:
        sums_cache.release()


def test_warm_decode_task_replaces_another_cameras_sums(tmp_path) -> None:
    """A worker that last decoded a smaller camera (a session's earlier rig, a preview
    camera) keeps its small sums: the warm task must still prime the large camera's, else
    the worker's first large pose pays ~2 CPU s of page faults while its frames arrive."""
    import numpy as np

    from acquisition.patterns import build_plan
    from calibration.decode import sums_cache
    from calibration.shared.plan import write_plan

    write_plan(build_plan(1920, 1080, 0.2745), tmp_path / "plan.json")
    sums_cache.keep([np.full((3, 16 * 12), 7.0)])
    try:
        warm_decode_task(64 * 48, str(tmp_path / "plan.json"), (48, 64))
        assert sums_cache.holds_pixels(48 * 64) and not sums_cache.holds_pixels(16 * 12)
    finally:
        sums_cache.release()


def test_warm_decode_task_primes_a_set_per_rig_camera(tmp_path) -> None:
    """A rig's cameras of one size decode at once, each with its own sums and (resident) maps
    buffer: the warm task keeps one of each per camera, and a second warm task with as many
    already kept allocates nothing; the first camera's maps file is laid out in a kept
    buffer."""
    from acquisition.patterns import build_plan
    from calibration.decode import sums_cache
    from calibration.shared.maps_file import MapsFile
    from calibration.shared.plan import write_plan
    from calibration.shared.resident_buffers import RESIDENT

    plan = build_plan(1920, 1080, 0.2745)
    write_plan(plan, tmp_path / "plan.json")
    sums_cache.release()
    RESIDENT.release()
    try:
        warm_decode_task(64 * 48, str(tmp_path / "plan.json"), (48, 64), None, 3,
                         resident_maps=True)
        assert sums_cache.holds_pixels(48 * 64, 3) and not sums_cache.holds_pixels(48 * 64, 4)
        kept = sums_cache.kept_arrays()
        buffers = RESIDENT.kept_bytes()
        assert buffers > 0 and buffers % 3 == 0
        warm_decode_task(64 * 48, str(tmp_path / "plan.json"), (48, 64), None, 3,
                         resident_maps=True)
        assert all(a is b for a, b in zip(sums_cache.kept_arrays(), kept, strict=True))
        assert RESIDENT.kept_bytes() == buffers
        with MapsFile(tmp_path / "maps.npz", (48, 64), plan.axes(), resident=True):
            assert RESIDENT.kept_bytes() == buffers * 2 // 3  # one of them taken
    finally:
        sums_cache.release()
        RESIDENT.release()


def test_warm_decode_task_warms_the_heap_after_allocating_the_sums(tmp_path, monkeypatch):
    """The sums' members under glibc's mmap threshold come from the heap: warmed before them,
    the free heap kept for the finishes' temporaries was taken by the sums, and the worker's
    next rig pose faulted its noise-line fits in afresh (~19000 pages at 4 x 5 MP). The warm
    heap is faulted in once the sums are allocated and kept."""
    from acquisition.patterns import build_plan
    from api.worker import tasks
    from calibration.decode import StreamingDecoder, sums_cache
    from calibration.shared.plan import write_plan

    write_plan(build_plan(1920, 1080, 0.2745), tmp_path / "plan.json")
    order: list[str] = []
    prepare = StreamingDecoder.prepare

    def prepared(self) -> None:
        prepare(self)
        order.append("sums")

    monkeypatch.setattr(StreamingDecoder, "prepare", prepared)
    monkeypatch.setattr(tasks, "_keep_heap", lambda pixels, decodes=1: order.append("heap"))
    sums_cache.release()
    try:
        warm_decode_task(64 * 48, str(tmp_path / "plan.json"), (48, 64), None, 2)
        assert order == ["sums", "sums", "heap"]
        order.clear()
        warm_decode_task(64 * 48, str(tmp_path / "plan.json"), (48, 64), None, 2)
        assert order == ["heap"]  # (sums already kept: the heap is still kept warm)
    finally:
        sums_cache.release()
