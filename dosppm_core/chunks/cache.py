"""Resident chunks under a memory limit, for every out-of-core mode.

OSPPM (one process) and each DOSPPM tracer keep their chunks in a
`ChunkCache`: chunks are activated one after another, round robin over the
chunks with work (`schedule.py` picks them), at most as many resident as the
memory limit allows, the least recently used evicted, and the next chunk
with work loaded on a background thread while the active one traces
(Günther & Grosch §3.1, "asynchronous loading").
"""
from __future__ import annotations

import ctypes
import time
from collections import OrderedDict
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass, field

import numpy as np

from dosppm_core.chunks.view import ChunkView


@dataclass
class ChunkCounters:
    """What the chunk machinery did: the numbers behind Figure 11."""
    activations: int = 0
    loads: int = 0
    load_seconds: float = 0.0       # reading files and building BVHs
    wait_seconds: float = 0.0       # of that, time the tracer sat waiting
    portal_rays: int = 0            # rays handed to another chunk
    wasted_prefetches: int = 0      # loaded ahead, then not used
    traced_batches: int = 0
    per_chunk_load: dict = field(default_factory=dict)


def _trim() -> None:
    """Return what an evicted chunk left in glibc's arenas (the loading
    thread's among them) to the system. Measured cycling the 34M-triangle
    building's chunks, two resident: 86 MiB kept after 30 loads without,
    26 with; OSPPM's sampled peak on it 401 -> 360 MiB, no slower. No-op
    off glibc."""
    try:
        ctypes.CDLL("libc.so.6").malloc_trim(0)
    except (OSError, AttributeError):
        pass


class ChunkCache:
    """Resident chunks under a memory limit, least recently used evicted,
    with one asynchronous prefetch."""

    def __init__(self, provider, memory_bytes: float, threads: int = 1):
        self.provider, self.threads = provider, threads
        self.memory = float(memory_bytes)
        self.cost = np.asarray(provider.chunk_memory, np.float64)
        self.resident: OrderedDict[int, ChunkView] = OrderedDict()
        self.counters = ChunkCounters()
        self._pool = ThreadPoolExecutor(1, thread_name_prefix="chunk-prefetch")
        self._pending: tuple[int, Future] | None = None

    def _load(self, k: int) -> tuple[ChunkView, float]:
        t0 = time.perf_counter()
        view = ChunkView(k, self.provider.load(k), self.provider.header, self.provider.tree,
                         threads=self.threads)
        return view, time.perf_counter() - t0

    def _make_room(self, k: int, keep: tuple) -> bool:
        """Evict least recently used chunks (never those in `keep`) until
        chunk k fits; False if it cannot fit beside them."""
        def used():
            return sum(self.cost[j] for j in self.resident) + \
                (self.cost[self._pending[0]] if self._pending else 0.0)
        while used() + self.cost[k] > self.memory:
            victim = next((j for j in self.resident if j not in keep), None)
            if victim is None:
                return False
            self.resident.pop(victim).close()
            _trim()
        return True

    def activate(self, k: int, ahead: int | None = None) -> ChunkView:
        """Chunk k, resident (loaded now if it must be); then start loading
        `ahead`, the next chunk with work, in the background."""
        view = self._activate(k)
        if ahead is not None and ahead != k:
            self.prefetch(ahead, active=k)
        return view

    @property
    def loading(self) -> int | None:
        """The chunk being loaded ahead, if any."""
        return self._pending[0] if self._pending else None

    def _activate(self, k: int) -> ChunkView:
        self.counters.activations += 1
        if k in self.resident:
            self.resident.move_to_end(k)
            return self.resident[k]
        t0 = time.perf_counter()
        got = self._prefetched() if self._pending and self._pending[0] == k else None
        if got is not None:
            view, seconds = got
        else:
            self._drop_prefetch()
            self._make_room(k, keep=())
            view, seconds = self._load(k)
        self.counters.wait_seconds += time.perf_counter() - t0
        self._count_load(k, seconds)
        self.resident[k] = view
        return view

    def prefetch(self, k: int, active: int) -> None:
        """Start loading chunk k in the background if memory allows it
        beside the active chunk."""
        if k in self.resident or (self._pending and self._pending[0] == k):
            return
        self._drop_prefetch()
        if self._make_room(k, keep=(active,)):
            self._pending = (k, self._pool.submit(self._load, k))

    def _prefetched(self):
        """(view, seconds) of the prefetch, or None if it failed: a provider
        may only load on the caller's thread (a tracer fetching a chunk over
        its sockets), and then the load is simply done at activation."""
        _, future = self._pending
        self._pending = None
        try:
            return future.result()
        except Exception:   # noqa: BLE001 - any failure is retried in the foreground
            return None

    def _drop_prefetch(self) -> None:
        if self._pending:
            got = self._prefetched()
            if got is not None:
                got[0].close()
                self.counters.wasted_prefetches += 1

    def _count_load(self, k: int, seconds: float) -> None:
        c = self.counters
        c.loads += 1
        c.load_seconds += seconds
        c.per_chunk_load[k] = c.per_chunk_load.get(k, 0) + 1

    def close(self) -> None:
        self._drop_prefetch()
        for view in self.resident.values():
            view.close()
        self.resident.clear()
        self._pool.shutdown(wait=True)
