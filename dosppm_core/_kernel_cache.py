"""Keep numba's on-disk cache honest across modules.

numba invalidates a cached function only when its own source file changes,
not when a function it calls from another file does: after an edit to
kernels/bsdf.py, a cached scatter kernel would keep running the old BSDF.
So the cache of the whole package is dropped whenever any module holding
kernels changes. A read-only install simply keeps what it has.
"""
from __future__ import annotations

import glob
import hashlib
import os

_HERE = os.path.dirname(os.path.abspath(__file__))
_STAMP = "dosppm-kernels.sha256"


def _kernel_sources() -> list[str]:
    """The modules that define numba functions (the others may change freely)."""
    paths = sorted(glob.glob(os.path.join(_HERE, "**", "*.py"), recursive=True))
    out = []
    for path in paths:
        with open(path, "rb") as f:
            if b"njit" in f.read():
                out.append(path)
    return out


def source_digest() -> str:
    h = hashlib.sha256()
    for path in _kernel_sources():
        h.update(os.path.relpath(path, _HERE).encode())
        with open(path, "rb") as f:
            h.update(f.read())
    return h.hexdigest()


def refresh() -> None:
    try:
        digest = source_digest()
        stamp = os.path.join(_HERE, "__pycache__", _STAMP)
        if os.path.exists(stamp) and open(stamp).read() == digest:
            return
        for path in glob.glob(os.path.join(_HERE, "**", "__pycache__", "*.nb[ic]"), recursive=True):
            os.remove(path)
        os.makedirs(os.path.dirname(stamp), exist_ok=True)
        with open(stamp, "w") as f:
            f.write(digest)
    except OSError:
        pass
