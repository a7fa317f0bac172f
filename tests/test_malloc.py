"""The C heap keeps no dropped chunk (dosppm_core/malloc.py): arrays of a
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
from dosppm_core.malloc import return_large_blocks
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


CACHE_CHILD = r"""
import sys
from dosppm_core.malloc import return_large_blocks
return_large_blocks()
from dosppm_core.chunks import cache
from dosppm_core.chunks.store import ChunkStore
if sys.argv[1] == "untrimmed":
    cache._trim = lambda: None
def rss_mib():
    return next(int(l.split()[1]) >> 10 for l in open("/proc/self/status") if l.startswith("VmRSS"))
store = ChunkStore.open(sys.argv[2])
c = cache.ChunkCache(store, 2.2 * max(store.chunk_memory), threads=1)
start, n = rss_mib(), store.tree.chunk_count
for i in range(5 * n):
    view = c.activate(i % n, ahead=(i + 1) % n)    # room for it and the one loading: every chunk evicted in turn
    del view
print(rss_mib() - start)
c.close()
"""


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="glibc's malloc_trim and /proc: Linux only")
def test_chunks_evicted_in_turn_leave_no_heap_behind(tmp_path):
    """OSPPM and tracers with more chunks than fit load and evict chunks
    for the whole render; what an evicted chunk leaves in glibc's arenas
    (the loading thread's among them) is trimmed at each eviction. On the
    34M-triangle building this took OSPPM's sampled peak from 401 to 360
    MiB. Control: the same cycle without the trim."""
    from tests.helpers.cli import run_dosppm
    soup, store = tmp_path / "building", tmp_path / "building.chunks"
    assert run_dosppm("scenes", "generate", "building", "--triangles", "1500000", "--out", soup).returncode == 0
    assert run_dosppm("subdivide", soup, "--chunks", "8", "--out", store).returncode == 0
    grown = {}
    for mode in ("trimmed", "untrimmed"):
        r = run_python("-c", CACHE_CHILD, mode, store, timeout=300)
        assert r.returncode == 0, r.stderr
        grown[mode] = int(r.stdout.split()[-1])
    print(f"RSS grown over 40 chunk loads with 2 resident: {grown} MiB")
    assert grown["untrimmed"] >= grown["trimmed"] + 8, grown


POLICY_CHILD = r"""
from dosppm_core import malloc
from dosppm_core.malloc import SERVER_MMAP_THRESHOLD_BYTES, return_large_blocks
first = return_large_blocks(SERVER_MMAP_THRESHOLD_BYTES)     # an entry point's choice
again = return_large_blocks(replace=False)                    # what a library mode (OSPPM) asks
print(first, again, malloc._fixed)
"""


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="glibc's mallopt: Linux only")
def test_a_library_mode_keeps_the_policy_its_process_chose():
    """One malloc policy per process: OSPPM's call (`replace=False`) no
    longer overrides the threshold the process's entry point set."""
    r = run_python("-c", POLICY_CHILD, timeout=60)
    assert r.returncode == 0, r.stderr
    assert r.stdout.split() == ["True", "False", str(128 << 10)]
