"""The live preview the operator page shows: scaled by the camera's full scale (a dark, idle
camera stays dark instead of showing stretched noise) and labelled with its source and level."""

from __future__ import annotations

import cv2
import numpy as np

from api.live_preview import full_scale, preview_image


def _decoded(jpeg: bytes) -> np.ndarray:
    return cv2.imdecode(np.frombuffer(jpeg, np.uint8), cv2.IMREAD_GRAYSCALE)


def test_dark_frame_stays_dark_and_says_so() -> None:
    rng = np.random.default_rng(3)
    dark = rng.integers(0, 6, size=(120, 160), dtype=np.uint16)  # idle Mono12: noise of a few DN
    shot = preview_image(dark, "Mono12", "idle")
    assert shot.source == "idle"
    assert shot.level < 0.01
    assert _decoded(shot.jpeg).max() <= 2  # not stretched to 255


def test_lit_frame_keeps_its_brightness() -> None:
    lit = np.full((120, 160), 2048, np.uint16)
    lit[:, :80] = 4095
    shot = preview_image(lit, "Mono12", "capture")
    img = _decoded(shot.jpeg)
    assert shot.source == "capture" and shot.level == 1.0
    assert abs(int(img[:, 100:].mean()) - 128) <= 2 and img[:, :40].mean() > 250


def test_full_scale_from_pixel_format() -> None:
    assert full_scale(np.zeros(1, np.uint16), "Mono12") == 4095
    assert full_scale(np.zeros(1, np.uint16), "Mono16") == 65535
    assert full_scale(np.zeros(1, np.uint8), "Mono8") == 255
    assert full_scale(np.zeros(1, np.uint16), None) == 65535
    assert full_scale(np.zeros(1, np.uint8), "Mono12") == 255  # more bits than the type holds
    assert full_scale(np.zeros(1, np.float32), "Mono12") == 1.0
