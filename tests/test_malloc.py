"""The C heap keeps no dropped chunk (services/malloc.py): arrays of a
chunk's size, each dropped after a small array is made that stays (a
message, a queue entry), are returned with the fixed mmap threshold and
pile up on the heap with glibc's default. The default is the control: it
shows the test can fail. Each case is a fresh child, so the heap is its own."""
from __future__ import annotations

import sys

import pytest

from tests.helpers.cli import run_python

CHILD = r"""
import sys, numpy as np
from services.malloc import return_large_blocks
fixed = return_large_blocks() if sys.argv[1] == "fixed" else None
def rss_mib():
    return next(int(l.split()[1]) >> 10 for l in open("/proc/self/status") if l.startswith("VmRSS"))
keep, start = [], rss_mib()
for i in range(60):
    chunk = np.ones((8 + i % 9) << 20, np.uint8)    # a chunk's array, 8-16 MiB
    keep.append(np.ones(64 << 10, np.uint8))       # something small that stays
    del chunk
print(fixed, rss_mib() - start)
"""


def _grown_mib(mode: str) -> tuple[str, int]:
    r = run_python("-c", CHILD, mode, timeout=120)
    assert r.returncode == 0, r.stderr
    fixed, grown = r.stdout.split()
    return fixed, int(grown)


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="glibc's mallopt and /proc: Linux only")
def test_dropped_chunk_arrays_are_returned_to_the_system():
    fixed, grown = _grown_mib("fixed")
    assert fixed == "True"            # glibc took the setting
    _, default_grown = _grown_mib("default")
    print(f"RSS grown over 60 dropped chunks: {grown} MiB fixed, {default_grown} MiB by glibc's default")
    assert grown < 8                  # the small arrays that stay: 60 x 64 KiB
    assert default_grown > 2 * grown + 8
