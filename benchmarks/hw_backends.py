"""Hardware backend throughput: framebuffer writes, pixel-format decoding, Aravis triggers.

Run: .venv/bin/python benchmarks/hw_backends.py
Prints one table; times are medians of repeated runs on this machine.
"""

from __future__ import annotations

import statistics
import tempfile
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

from acquisition.camera.pixel_formats import decode_image, pack_mono12, pixel_format
from acquisition.display.framebuffer import FramebufferDisplay, FramebufferGeometry


def _median_ms(fn: Callable[[], object], repeat: int) -> float:
    fn()
    times = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return 1e3 * statistics.median(times)


def framebuffer_rows(w: int = 1920, h: int = 1080) -> list[tuple[str, float]]:
    """Encode + mmap write of one full-screen frame (no vsync wait: period 1 us)."""
    rows = []
    img = np.random.default_rng(0).integers(0, 256, (h, w)).astype(np.uint8)
    for bpp in (16, 24, 32):
        geo = FramebufferGeometry.standard(w, h, bpp, refresh_hz=1e6)
        path = Path(tempfile.mktemp(prefix="phasecal-bench-fb-", dir="/dev/shm"))
        path.write_bytes(bytes(geo.size_bytes))
        d = FramebufferDisplay(path, geometry=geo)
        rows.append((f"framebuffer show {w}x{h} {bpp} bpp", _median_ms(lambda d=d: d.show(img),
                                                                         15)))
        d.close()
        path.unlink()
    return rows


def decode_rows(w: int = 1920, h: int = 1200) -> list[tuple[str, float]]:
    """Raw buffer -> grey image for packed and Bayer formats."""
    rng = np.random.default_rng(1)
    v12 = rng.integers(0, 4096, (h, w)).astype(np.uint16)
    v8 = rng.integers(0, 256, (h, w)).astype(np.uint8)
    cases = {
        "Mono8": v8.tobytes(),
        "Mono16": v12.astype("<u2").tobytes(),
        "Mono12Packed": pack_mono12(v12, "mono12packed"),
        "Mono12p": pack_mono12(v12, "mono12p"),
        "BayerRG8": v8.tobytes(),
        "BayerRG12Packed": pack_mono12(v12, "mono12packed"),
    }
    rows = []
    for name, data in cases.items():
        fmt = pixel_format(name)
        ms = _median_ms(lambda d=data, f=fmt: decode_image(d, f, w, h), 7)
        rows.append((f"decode {name} {w}x{h}", ms))
    return rows


def aravis_rows(frames: int = 30) -> list[tuple[str, float]]:
    """Software trigger -> grab round trip through the GigE Vision fake on loopback."""
    from acquisition.camera.aravis_camera import AravisCamera
    from acquisition.camera.aravis_fake import FakeGigECamera, fake_camera_lock
    from acquisition.camera.aravis_gi import aravis_available
    from acquisition.errors import FrameLost
    from acquisition.protocols import CameraSettings

    if not aravis_available():
        return [("aravis (not installed)", float("nan"))]
    rows = []
    with fake_camera_lock():
        fake = FakeGigECamera("PHASECAL-BENCH", lambda r: np.zeros((r.height, r.width),
                                                                    np.uint8))
        for w, h in ((64, 48), (640, 480)):
            cam = AravisCamera("127.0.0.1", region=(0, 0, w, h))
            cam.configure(CameraSettings(exposure_s=0.001, trigger_mode="software"))
            cam.start()

            def shot(cam=cam) -> None:
                """One trigger-to-frame round trip; a frame lost on the link is triggered
                again, as the controller does, and its time counts."""
                for _ in range(4):
                    cam.trigger()
                    try:
                        cam.grab(2.0)
                        return
                    except FrameLost:
                        continue
                raise FrameLost("four frames in a row lost on the loopback link")

            rows.append((f"aravis fake trigger->frame {w}x{h} Mono8",
                         _median_ms(shot, frames)))
            cam.close()
        fake.stop()
    return rows


def main() -> None:
    rows = framebuffer_rows() + decode_rows() + aravis_rows()
    width = max(len(name) for name, _ in rows)
    print(f"{'case'.ljust(width)}  median ms")
    for name, ms in rows:
        print(f"{name.ljust(width)}  {ms:9.2f}")


if __name__ == "__main__":
    main()
