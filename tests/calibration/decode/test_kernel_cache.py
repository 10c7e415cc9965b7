"""The decoder's numba cache is dropped when any kernel source changes (numba alone only
notices a change to the kernel's own file, not to code it inlines from another)."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path
from types import SimpleNamespace

from calibration.decode.kernel_cache import drop_stale_kernels, sources_digest


def _fake_kernel(cache_dir: Path, flushed: list[str]) -> SimpleNamespace:
    cache = SimpleNamespace(cache_path=str(cache_dir), flush=lambda: flushed.append("flush"))
    return SimpleNamespace(_cache=cache, py_func=SimpleNamespace(__module__="fake"))


def test_cache_dropped_once_per_new_digest(tmp_path: Path) -> None:
    flushed: list[str] = []
    ns = {"__name__": "fake", "k": _fake_kernel(tmp_path, flushed), "n": 3}
    assert drop_stale_kernels(ns, "d1") == ["k"] and flushed == ["flush"]
    assert drop_stale_kernels(ns, "d1") == [] and flushed == ["flush"]
    assert drop_stale_kernels(ns, "d2") == ["k"] and len(flushed) == 2
    assert (tmp_path / "fake.k.sources").read_text() == "d2"


def test_imported_kernels_are_stamped_with_the_current_sources() -> None:
    from calibration.decode.kernel_sums import finish_sums

    name = "calibration.decode.kernel_sums.finish_sums.sources"
    stamp = Path(finish_sums._cache.cache_path) / name
    assert stamp.read_text() == sources_digest()


_KERNEL = """
import hashlib, pathlib
from numba import njit
from calibration.decode.kernel_cache import drop_stale_kernels
from helper import value

@njit(cache=True)
def kernel():
    return value()

here = pathlib.Path(__file__).parent
drop_stale_kernels(globals(), hashlib.sha1((here / "helper.py").read_bytes()).hexdigest())
print(kernel())
"""


def test_a_changed_inlined_helper_is_compiled_again(tmp_path: Path) -> None:
    """A cached kernel whose own file is unchanged picks up its helper's new code."""
    (tmp_path / "kern.py").write_text(_KERNEL)
    helper = "from numba import njit\n\n@njit(cache=True, inline='always')\ndef value():\n"

    def run(result: int) -> str:
        (tmp_path / "helper.py").write_text(helper + f"    return {result}\n")
        out = subprocess.run([sys.executable, str(tmp_path / "kern.py")], capture_output=True,
                             text=True, cwd=tmp_path, check=True)
        return out.stdout.strip()

    assert run(1) == "1"
    assert run(2) == "2"
