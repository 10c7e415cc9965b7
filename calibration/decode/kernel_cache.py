"""Keeps numba's on-disk cache of the decoder's kernels in step with all of their sources.

numba keys a cached kernel on its own file's timestamp only, so a kernel that inlines code
from another file (`finish_sums` calls `unwrap_block`, `fit_block`, `atan2_f32`, ...)
would keep stale machine code after an update that changed only that other file. Each
kernel module calls `drop_stale_kernels(globals())` right after defining its kernels, before
any of them runs: when the digest of every kernel source differs from the one recorded
beside a kernel's cache, that cache is emptied and the kernel compiles afresh once."""

from __future__ import annotations

import functools
import hashlib
from pathlib import Path
from typing import Any


@functools.lru_cache(maxsize=1)
def sources_digest(folder: Path = Path(__file__).parent) -> str:
    """SHA-1 over the names and contents of the package's kernel sources: every module that
    defines a numba kernel (whatever a kernel inlines is one of them), so a new kernel file
    needs no list kept by hand."""
    digest = hashlib.sha1()
    for path in sorted(folder.glob("*.py")):
        text = path.read_bytes()
        if b"@njit" in text:
            digest.update(path.name.encode() + b"\0" + text)
    return digest.hexdigest()


def drop_stale_kernels(namespace: dict[str, Any], digest: str | None = None) -> list[str]:
    """Empty the on-disk cache of each cached kernel defined in `namespace` (a module's
    globals) whose recorded sources digest is not `digest` (default: the current one), and
    record it. Returns the kernels dropped. A cache folder that cannot be written is left to
    numba (it compiles in memory)."""
    digest = digest or sources_digest()
    module = namespace.get("__name__")
    dropped = []
    for name, obj in namespace.items():
        cache = getattr(obj, "_cache", None)  # numba's Dispatcher: its FunctionCache
        folder = getattr(cache, "cache_path", None)
        if folder is None or getattr(obj.py_func, "__module__", None) != module:
            continue  # not a cached kernel of this module (or the JIT is disabled)
        stamp = Path(folder) / f"{module}.{name}.sources"
        try:
            if stamp.is_file() and stamp.read_text() == digest:
                continue
            cache.flush()
            stamp.write_text(digest)
        except OSError:
            continue
        dropped.append(name)
    return dropped
