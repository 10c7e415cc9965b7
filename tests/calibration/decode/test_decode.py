"""Decoder unit tests on an analytic rendering (exact truth): streaming, statistics, bad input, CLI.

The hw_mocks end-to-end checks (optics, sensor, display gamma) are in test_decode_hwmocks.py.
"""

from __future__ import annotations

import numpy as np
import pytest

from acquisition.patterns import build_plan
from api.cli import main as cli_main
from calibration.decode import (
    DecodeError,
    DecodeOptions,
    NoiseModel,
    StreamingDecoder,
    decode_stack,
)
from calibration.shared.maps import load_maps
from calibration.shared.plan import FlatFrame, Plan, write_plan

H, W = 192, 256


@pytest.fixture(scope="module")
def plan() -> Plan:
    return build_plan(1920, 1080, 0.2745)


def render(
    plan: Plan,
    *,
    read: float = 1.5,
    gain_e_per_dn: float | None = None,
    white: float = 200.0,
    dark: float = 10.0,
    blur: float = 0.0,
    seed: int = 0,
    x0: float = 100.0,
    dtype=np.uint8,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Frames of a smooth pixel -> screen mapping with Gaussian blur and sensor noise."""
    rng = np.random.default_rng(seed)
    u, v = np.meshgrid(np.arange(W, dtype=np.float64), np.arange(H, dtype=np.float64))
    x = x0 + 6.3 * u + 0.002 * (u - 128) ** 2 + 0.3 * v
    y = 80 + 5.1 * v + 0.001 * (v - 96) ** 2 - 0.2 * u
    sw, sh = plan.screen.width_px, plan.screen.height_px
    on = (x > -0.5) & (x < sw - 0.5) & (y > -0.5) & (y < sh - 0.5)
    frames = []
    for f in plan.frames:
        if isinstance(f, FlatFrame):
            lin = np.full(x.shape, f.level)
        else:
            c = x if f.axis == "x" else y
            att = np.exp(-2 * np.pi**2 * blur**2 / f.period_px**2)
            lin = f.offset + f.amplitude * att * np.cos(2 * np.pi * c / f.period_px + f.phase_shift)
        val = dark + (white - dark) * np.where(on, lin, 0.0)
        var = read**2 + (0.0 if gain_e_per_dn is None else val / gain_e_per_dn)
        val = val + rng.normal(0.0, 1.0, val.shape) * np.sqrt(var)
        if dtype == np.float32:
            frames.append(val.astype(np.float32))
        else:
            frames.append(np.clip(np.rint(val), 0, np.iinfo(dtype).max).astype(dtype))
    return np.stack(frames), x, y


def zscores(maps, x: np.ndarray, y: np.ndarray) -> list[np.ndarray]:
    m = maps.mask
    return [((maps.x - x) / maps.sigma_x)[m], ((maps.y - y) / maps.sigma_y)[m]]


def check_honest(maps, x, y) -> None:
    for z in zscores(maps, x, y):
        assert 0.8 <= z.std() <= 1.25, z.std()
        assert abs(z.mean()) <= 0.1, z.mean()
        assert np.sqrt(np.mean(z**2)) <= 1.2


@pytest.mark.parametrize(
    ("read", "white", "blur", "noise_given"),
    [
        (1.5, 200.0, 0.0, False),
        (3.0, 200.0, 3.0, True),
        (1.0, 60.0, 6.0, False),
        (4.0, 120.0, 1.0, True),
    ],
)
def test_errors_match_predicted_sigma(plan, read, white, blur, noise_given):
    stack, x, y = render(plan, read=read, white=white, blur=blur, seed=int(read * 10))
    noise = (read**2 + 1 / 12) ** 0.5 if noise_given else None
    maps = decode_stack(plan, stack, noise=noise)
    assert maps.mask.mean() > 0.97
    check_honest(maps, x, y)


def test_shot_noise_residual_mode_fits_photon_transfer(plan):
    stack, x, y = render(plan, read=1.0, gain_e_per_dn=0.5, white=220.0, seed=3)
    maps = decode_stack(plan, stack)
    check_honest(maps, x, y)
    model = NoiseModel(read_dn=1.0, gain_e_per_dn=0.5)
    check_honest(decode_stack(plan, stack, noise=model), x, y)


def test_photon_transfer_from_spread_sample_matches_full_fit(plan, monkeypatch):
    """Large images fit the noise line on spread pieces: same line, honest sigma."""
    import calibration.decode.decoder as decoder_module

    stack, x, y = render(plan, read=1.0, gain_e_per_dn=0.5, white=220.0, seed=4)
    full = decode_stack(plan, stack).meta["decoder"]["photon_transfer"]
    monkeypatch.setattr(decoder_module, "_NOISE_PIECE", 1024)
    monkeypatch.setattr(decoder_module, "_NOISE_SAMPLE", H * W // 3)
    maps = decode_stack(plan, stack)
    sampled = maps.meta["decoder"]["photon_transfer"]
    assert sampled["slope"] == pytest.approx(full["slope"], rel=0.15)
    assert sampled["offset"] + 100 * sampled["slope"] == pytest.approx(
        full["offset"] + 100 * full["slope"], rel=0.05
    )
    check_honest(maps, x, y)


def test_streaming_any_order_matches_stack(plan):
    stack, *_ = render(plan, seed=5)
    ref = decode_stack(plan, stack, noise=1.5)
    dec = StreamingDecoder(plan, (H, W), noise=1.5)
    for i in np.random.default_rng(1).permutation(len(plan.frames)):
        dec.add(int(i), stack[i])
    got = dec.finish({"pose": 3})
    assert got.meta["pose"] == 3 and got.meta["plan_digest"] == plan.digest()
    np.testing.assert_array_equal(got.mask, ref.mask)
    np.testing.assert_allclose(got.x[got.mask], ref.x[ref.mask], atol=1e-4)
    np.testing.assert_allclose(got.sigma_y[got.mask], ref.sigma_y[ref.mask], rtol=1e-4)


def test_saturated_samples_are_excluded_not_biasing(plan):
    # white 320 DN on an 8-bit camera: the top of every cosine clips at 255.
    stack, x, y = render(plan, white=320.0, read=1.5, seed=7)
    assert (stack == 255).mean() > 0.1
    maps = decode_stack(plan, stack, noise=(1.5**2 + 1 / 12) ** 0.5)
    assert maps.mask.mean() > 0.97
    check_honest(maps, x, y)
    # Without exclusion (saturation level above the data) the clipped tops bias the phase.
    biased = decode_stack(plan, stack.astype(np.float32), noise=1.5)
    zb = np.concatenate(zscores(biased, x, y))
    assert np.sqrt(np.mean(zb**2)) > 2.0


def test_blur_estimate(plan):
    for blur in (2.0, 4.0, 8.0):
        stack, *_ = render(plan, blur=blur, read=1.0, seed=11)
        maps = decode_stack(plan, stack)
        for b in (maps.blur_x, maps.blur_y):
            assert abs(np.nanmedian(b[maps.mask]) / blur - 1.0) < 0.1
            assert np.nanpercentile(np.abs(b[maps.mask] / blur - 1.0), 90) < 0.25


def test_pixels_seeing_no_screen_are_invalid(plan):
    stack, x, y = render(plan, x0=-600.0, seed=13)  # the left part of the image sees no screen
    maps = decode_stack(plan, stack)
    off = (x < -3) | (x > plan.screen.width_px + 2)
    assert off.mean() > 0.2
    assert not maps.mask[off].any()
    assert maps.mask[~off & (x > 3)].mean() > 0.97
    assert maps.meta["pixel_counts"]["no_screen"] >= off.sum() * 0.9
    check_honest(maps, x, y)


def test_low_contrast_pixels_flagged_not_guessed(plan):
    # Vignetting ramp: contrast falls from 90 DN (left) to 2 DN (right).
    white = np.broadcast_to(np.linspace(100.0, 12.0, W)[None, :], (H, W))
    stack, x, y = render(plan, white=white, dark=10.0, read=2.0, seed=17)
    maps = decode_stack(plan, stack)
    check_honest(maps, x, y)
    assert maps.mask[:, : W // 4].mean() > 0.97
    assert not maps.mask[:, -W // 16 :].any()
    counts = maps.meta["pixel_counts"]
    assert counts["no_screen"] + counts["low_modulation"] + counts["uncertain"] > H * W // 8


def test_uint16_and_float32_frames(plan):
    for dtype, white in ((np.uint16, 3000.0), (np.float32, 0.8)):
        read = 4.0 if dtype == np.uint16 else 0.004
        stack, x, y = render(plan, white=white, dark=white / 20, read=read, dtype=dtype, seed=19)
        check_honest(decode_stack(plan, stack), x, y)


# -- bad input ------------------------------------------------------------------------


def test_bad_frames_give_clear_errors(plan):
    stack, *_ = render(plan, seed=23)
    dec = StreamingDecoder(plan, (H, W))
    with pytest.raises(DecodeError, match="shape"):
        dec.add(0, stack[0][:, :-1])
    with pytest.raises(DecodeError, match="dtype int32"):
        dec.add(0, stack[0].astype(np.int32))
    with pytest.raises(DecodeError, match="single-channel"):
        dec.add(0, np.dstack([stack[0]] * 3))
    with pytest.raises(DecodeError, match="out of range"):
        dec.add(len(plan.frames), stack[0])
    dec.add(0, stack[0])
    with pytest.raises(DecodeError, match="already added"):
        dec.add(0, stack[0])
    with pytest.raises(DecodeError, match="differs from the earlier"):
        dec.add(1, stack[1].astype(np.uint16))
    with pytest.raises(DecodeError, match=r"missing, first \[1, 2"):
        dec.finish()
    with pytest.raises(DecodeError, match="the plan has"):
        decode_stack(plan, stack[:-1])


def test_all_dark_stack_is_an_error(plan):
    rng = np.random.default_rng(0)
    stack = rng.integers(8, 13, size=(len(plan.frames), H, W)).astype(np.uint8)
    with pytest.raises(DecodeError, match="no pixel sees the screen"):
        decode_stack(plan, stack)


def test_options_are_validated():
    with pytest.raises(ValueError, match="max_sigma_px"):
        DecodeOptions(max_sigma_px=0)
    with pytest.raises(ValueError, match="max_ambiguity"):
        DecodeOptions(max_ambiguity=2.0)


# -- command line -----------------------------------------------------------------------


def test_cli_decode_npy_and_png_folder(plan, tmp_path, capsys):
    import cv2

    stack, x, y = render(plan, seed=29)
    write_plan(plan, tmp_path / "plan.json")
    np.save(tmp_path / "frames.npy", stack)
    out = tmp_path / "maps.npz"
    rc = cli_main(["decode", "--plan", str(tmp_path / "plan.json"), "--frames",
                   str(tmp_path / "frames.npy"), "--noise-dn", "1.53", "-o", str(out)])
    assert rc == 0
    maps = load_maps(out)
    check_honest(maps, x, y)
    folder = tmp_path / "frames"
    folder.mkdir()
    for i, f in enumerate(stack):
        cv2.imwrite(str(folder / f"frame_{i:04d}.png"), f.astype(np.uint16) * 16)
    out2 = tmp_path / "maps2.npz"
    assert cli_main(["decode", "--plan", str(tmp_path / "plan.json"), "--frames", str(folder),
                     "-o", str(out2)]) == 0
    check_honest(load_maps(out2), x, y)
    capsys.readouterr()
    (folder / "frame_0005.png").unlink()
    rc = cli_main(["decode", "--plan", str(tmp_path / "plan.json"), "--frames", str(folder),
                   "-o", str(out2)])
    err = capsys.readouterr().err.strip()
    assert rc == 1 and "missing" in err and "\n" not in err
    np.save(tmp_path / "short.npy", stack[:5])
    rc = cli_main(["decode", "--plan", str(tmp_path / "plan.json"), "--frames",
                   str(tmp_path / "short.npy"), "-o", str(out2)])
    err = capsys.readouterr().err.strip()
    assert rc == 1 and "5 frames" in err and "\n" not in err
    np.save(tmp_path / "bad.npy", stack.astype(np.int16))
    rc = cli_main(["decode", "--plan", str(tmp_path / "plan.json"), "--frames",
                   str(tmp_path / "bad.npy"), "-o", str(out2)])
    assert rc == 1 and "int16" in capsys.readouterr().err


def test_generic_array_namespace_path_matches_opencv_path(plan):
    """The code path used for CuPy (plain xp array ops, no OpenCV) gives the same maps."""
    import types

    proxy = types.ModuleType("numpy_proxy")
    proxy.__dict__.update({k: getattr(np, k) for k in dir(np) if not k.startswith("__")})
    stack, x, y = render(plan, white=320.0, seed=31)  # with clipped samples
    ref = decode_stack(plan, stack)
    got = decode_stack(plan, stack, xp=proxy)
    np.testing.assert_array_equal(got.mask, ref.mask)
    np.testing.assert_allclose(got.x[got.mask], ref.x[ref.mask], atol=1e-4)
    np.testing.assert_allclose(got.sigma_x[got.mask], ref.sigma_x[ref.mask], rtol=1e-3)
    check_honest(got, x, y)


def assert_same_maps(got, ref) -> None:
    """Equal to float32 rounding: same pixels, positions, sigmas and modulations."""
    assert got.meta["pixel_counts"] == ref.meta["pixel_counts"]
    assert got.meta["decoder"]["photon_transfer"] == ref.meta["decoder"]["photon_transfer"]
    assert got.meta["decoder"]["max_sample_dn"] == ref.meta["decoder"]["max_sample_dn"]
    np.testing.assert_array_equal(got.mask, ref.mask)
    for key in ("x", "y"):
        np.testing.assert_allclose(getattr(got, key), getattr(ref, key), atol=1e-6,
                                   equal_nan=True)
    for key in ("sigma_x", "sigma_y", "modulation_x", "modulation_y"):
        np.testing.assert_allclose(getattr(got, key), getattr(ref, key), rtol=1e-5,
                                   equal_nan=True)
    for key in ("blur_x", "blur_y"):
        np.testing.assert_allclose(getattr(got, key), getattr(ref, key), atol=5e-3,
                                   equal_nan=True)


@pytest.mark.parametrize("noise", [None, 1.5, NoiseModel(read_dn=1.5, gain_e_per_dn=1e3,
                                                          black_dn=8.0)])
def test_compiled_decoder_matches_array_namespace_path(plan, monkeypatch, noise):
    """The numba kernels (large images, once loaded) equal the array-namespace path: the
    cache-blocked accumulation frame by frame, in batches (a frame store's map) and range
    by range over a whole stack (`decode_stack`), each with the compiled finish."""
    import calibration.decode.decoder as decoder_module
    from calibration.decode.kernel_warm import warm_up

    warm_up()
    stack, x, y = render(plan, white=320.0, blur=1.5, seed=37)  # clipped samples, blur
    stack[:, :, :6] = 0  # a black border: every step clipped (no fit)
    monkeypatch.setattr(decoder_module, "COMPILED_MIN_PIXELS", 1 << 40)
    ref = decode_stack(plan, stack, noise=noise)
    assert ref.meta["pixel_counts"]["no_screen"] >= 6 * H
    monkeypatch.setattr(decoder_module, "COMPILED_MIN_PIXELS", 0)
    whole = decode_stack(plan, stack, noise=noise)
    check_honest(whole, x, y)
    # In plan order: float32 sums in another order round differently, and the residual
    # noise line follows (test_streaming_any_order_matches_stack covers any order).
    streamed = StreamingDecoder(plan, (H, W), noise=noise)
    for i in range(5):
        streamed.add(i, stack[i])
    store = np.ascontiguousarray(stack[::-1])  # frames in other rows of a store
    last = len(plan.frames) - 1
    for batch in np.array_split(np.arange(5, last + 1), 3):  # frames landed since the last look
        streamed.add_frames(batch.tolist(), store, rows=(last - batch).tolist())
    for got in (whole, streamed.finish()):
        assert_same_maps(got, ref)


@pytest.mark.parametrize("noise", [None, 1.5])
def test_compiled_decoder_fits_partly_clipped_pixels_itself(plan, monkeypatch, noise):
    """Pixels with some steps clipped (every pixel of this stack) are fitted by the compiled
    kernels (kernel_clipped.py), in the finish and in the noise estimate's first pass: the
    array path is never asked for them."""
    import calibration.decode.decoder as decoder_module
    from calibration.decode.kernel_warm import warm_up

    warm_up()
    stack, x, y = render(plan, white=320.0, blur=1.5, seed=41)
    assert ((stack >= 250).any(axis=0) & ~(stack >= 250).all(axis=0)).all()

    def refuse(*args, **kwargs):
        raise AssertionError("array path used")

    monkeypatch.setattr(decoder_module, "COMPILED_MIN_PIXELS", 0)
    monkeypatch.setattr(decoder_module.StreamingDecoder, "_finish_arrays", refuse)
    monkeypatch.setattr(decoder_module.StreamingDecoder, "_residual_arrays", refuse)
    check_honest(decode_stack(plan, stack, noise=noise), x, y)


def test_photon_transfer_with_constant_pixels_at_the_black_level():
    """Pixels reading one constant value (residual 0: a black level under the noise floor)
    used to put an infinite weight into the line fit (LinAlgError); their bin sits at the
    quantization floor and the line follows the others."""
    from calibration.decode.ptc_fit import fit_photon_transfer

    rng = np.random.default_rng(3)
    mean = np.concatenate([np.full(8000, 6.0), rng.uniform(20.0, 200.0, 30000)])
    var = np.where(mean > 6.0, 0.1 + 0.02 * mean, 0.0)
    rss = var * rng.chisquare(7, mean.size)
    line = fit_photon_transfer(mean, rss, np.full(mean.size, 7.0), 1.0 / 12.0)
    assert line is not None and abs(line.slope - 0.02) < 0.003, line


def test_ready_frames_holds_back_incomplete_period_groups(plan):
    """A live decoder adds the flats at once and a period group's frames once all of them
    are stored (one cache-blocked pass per group); adding them so gives the stack's maps."""
    stack, *_ = render(plan, seed=5)
    ref = decode_stack(plan, stack, noise=1.5)
    dec = StreamingDecoder(plan, (H, W), noise=1.5)
    groups = [ps.frame_indices for ps in plan.period_sets()]
    flats = [i for i in range(len(plan.frames)) if all(i not in g for g in groups)]
    partial = list(groups[0][:-1])
    assert dec.ready_frames(flats + partial) == sorted(flats)
    dec.add_frames(flats, stack, rows=flats)
    stored = partial
    for group in groups:
        stored = sorted(set(stored) | set(group))
        ready = dec.ready_frames(stored)
        assert ready == sorted(group)
        dec.add_frames(ready, stack, rows=ready)
        stored = []
    assert dec.missing == []
    got = dec.finish()
    np.testing.assert_array_equal(got.mask, ref.mask)
    np.testing.assert_allclose(got.x[got.mask], ref.x[ref.mask], atol=1e-4)


def test_ready_frames_passes_the_last_group_frame_by_frame(plan):
    """Once one period group is left, a live decoder adds its frames as they come (so the
    pass after a live pose's last frame reads one frame); the maps are the stack's."""
    stack, *_ = render(plan, seed=5)
    ref = decode_stack(plan, stack, noise=1.5)
    dec = StreamingDecoder(plan, (H, W), noise=1.5)
    last = list(plan.period_sets()[-1].frame_indices)
    first = [i for i in range(len(plan.frames)) if i not in last]
    assert dec.ready_frames([last[0]]) == []  # other groups are still missing
    dec.add_frames(first, stack, rows=first)
    for i in last:
        assert dec.ready_frames([i]) == [i]
        dec.add_frames([i], stack, rows=[i])
    got = dec.finish()
    np.testing.assert_array_equal(got.mask, ref.mask)
    np.testing.assert_allclose(got.x[got.mask], ref.x[ref.mask], atol=1e-4)
    np.testing.assert_allclose(got.y[got.mask], ref.y[ref.mask], atol=1e-4)


def test_compiled_decoder_with_display_harmonic_matches_array_path(monkeypatch):
    """A 6-step plan through a display gamma: the residual's harmonic N/2 is fitted and
    subtracted (`harmonic_leak`); the compiled path does the same (float32 rounding)."""
    import calibration.decode.decoder as decoder_module
    from calibration.decode.kernel_warm import warm_up

    warm_up()
    plan6 = build_plan(1920, 1080, 0.2745, steps=6)
    stack, _, _ = render(plan6, white=240.0, read=0.8, seed=3)
    stack = np.clip(np.rint(255.0 * (stack / 255.0) ** 1.8), 0, 255).astype(np.uint8)
    monkeypatch.setattr(decoder_module, "COMPILED_MIN_PIXELS", 1 << 40)
    ref = decode_stack(plan6, stack)
    monkeypatch.setattr(decoder_module, "COMPILED_MIN_PIXELS", 0)
    got = decode_stack(plan6, stack)
    leak = ref.meta["decoder"]["display_harmonic_r2"]
    assert leak is not None
    np.testing.assert_allclose(got.meta["decoder"]["display_harmonic_r2"], leak, rtol=1e-4)
    assert got.meta["pixel_counts"] == ref.meta["pixel_counts"]
    for key in ("x", "y"):
        np.testing.assert_allclose(getattr(got, key), getattr(ref, key), atol=1e-5,
                                   equal_nan=True)
    for key in ("sigma_x", "sigma_y"):
        np.testing.assert_allclose(getattr(got, key), getattr(ref, key), rtol=1e-4,
                                   equal_nan=True)


def test_residual_noise_keeps_the_partly_clipped_pixels_a_given_noise_keeps(plan, monkeypatch):
    """Noise from residuals on a noisy camera whose brightest steps clip: the fits on partial
    steps model the same harmonics as with the noise given (harmonic 3 used to leave them
    no residual dof and 10-150x the fundamental's variance: a third of such pixels failed
    `min_modulation_snr`), their larger residual dof stay within the kernel's chi-square
    table, and the compiled finish equals the array path."""
    import calibration.decode.decoder as decoder_module
    from calibration.decode.kernel_warm import warm_up

    warm_up()
    stack, x, y = render(plan, white=290.0, dark=6.0, read=1.5, gain_e_per_dn=4.0, seed=43)
    some = (stack >= 250).any(axis=0) & ~(stack >= 250).all(axis=0)
    assert some.mean() > 0.5
    given = decode_stack(plan, stack, noise=NoiseModel(read_dn=1.5, gain_e_per_dn=4.0,
                                                       black_dn=0.0))
    monkeypatch.setattr(decoder_module, "COMPILED_MIN_PIXELS", 1 << 40)
    ref = decode_stack(plan, stack, noise=None)
    monkeypatch.setattr(decoder_module, "COMPILED_MIN_PIXELS", 0)
    got = decode_stack(plan, stack, noise=None)
    assert_same_maps(got, ref)
    check_honest(got, x, y)
    assert got.mask.sum() >= 0.995 * given.mask.sum()
    low = [m.meta["pixel_counts"]["low_modulation"] for m in (got, given)]
    assert low[0] <= low[1] + 0.002 * got.mask.size, low
