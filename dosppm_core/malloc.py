"""The C heap of a dosppm process, one policy for every role: chunks are
loaded and dropped over and over (a tracer with more chunks than fit,
OSPPM, the subdivider), and glibc's default keeps the memory of dropped
chunks. Rendering processes (tracers, OSPPM, `dosppm render`'s children)
fix the mmap threshold at MMAP_THRESHOLD_BYTES, the server at
SERVER_MMAP_THRESHOLD_BYTES; the chunk cache also trims after an eviction
(chunks/cache.py).

glibc serves a large block with mmap and returns it on free, but each time
such a block is freed it raises its threshold for mmap to that block's size
(up to 32 MiB). After the first chunk is dropped, chunk-sized arrays come
from the heap, and loading and dropping chunks of different sizes leaves it
fragmented and never returned: a tracer cycling 8 chunks of 64 MiB, one
resident at a time, grew from 240 to 380 MiB in 8 s (500 MiB in one CI
run). A fixed threshold turns that off."""
from __future__ import annotations

import ctypes
import os

M_MMAP_THRESHOLD = -3        # mallopt's parameter number (malloc.h)
# Chunk arrays and Embree's buffers (MiB and up) are mmapped and returned on
# free; ray batches and messages (32k rays: under 2 MiB) stay on the heap,
# which is as fast as before (measured: `dosppm render --time 20`, medians of
# 3, 542k photons/s by default, 556k with 4 MiB; 128 KiB cost a fifth).
MMAP_THRESHOLD_BYTES = 4 << 20
# The server holds the deposits of the jobs in flight as the messages they
# came in (about 1 MiB each), drops them as jobs complete and batches go
# out, and keeps new ones meanwhile: on the heap they leave it fragmented.
# glibc's own starting threshold, kept fixed, returns them: the server's
# peak on the 6M-triangle building (server + 2 workers, 8 s) fell from
# 458-462 MiB to 377-381 (429-436 at 512 KiB).
SERVER_MMAP_THRESHOLD_BYTES = 128 << 10


_fixed: int | None = None      # the threshold this process was given


def return_large_blocks(threshold: int = MMAP_THRESHOLD_BYTES, replace: bool = True) -> bool:
    """Fix glibc's mmap threshold for this process, unless the user set one
    (MALLOC_MMAP_THRESHOLD_). `replace` False: only if the process has no
    policy yet (a library mode such as OSPPM keeps the one its entry point
    chose). False where the C library is not glibc."""
    global _fixed
    if "MALLOC_MMAP_THRESHOLD_" in os.environ or (_fixed is not None and not replace):
        return False
    try:
        libc = ctypes.CDLL("libc.so.6")
        ok = bool(libc.mallopt(M_MMAP_THRESHOLD, int(threshold)))
    except (OSError, AttributeError):
        return False
    if ok:
        _fixed = int(threshold)
    return ok
