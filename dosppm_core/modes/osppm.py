"""OSPPM: out-of-core SPPM in one process (Günther & Grosch §3.1).

The scene lives in chunks (a chunk store on disk, or any object with
`header`, `tree`, `chunk_memory` and `load(k)`). Each chunk has a queue of
pending ray batches. Chunks are activated one after another, round robin,
with at most as many resident as the memory limit allows; the next chunk
with work is loaded on a background thread while the active one traces.
All batches queued for the active chunk are coalesced into one (client
batching, §4.3), so packages that split at portals merge again instead of
multiplying.

An iteration is an eye phase (hit points of every pixel) and a photon
phase, then the statistics update, exactly as in `render.Renderer`; the
kernels, job records and statistics are the same, so the same seed gives
the same image whatever the number of chunks, up to floating-point noise.
"""
from __future__ import annotations

import time
from collections import OrderedDict
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass, field

import numpy as np

from dosppm_core.chunks.view import ChunkView, start_chunks, trace_eye_in_chunk, trace_photons_in_chunk
from dosppm_core.jobs import END_NAMES, ESCAPED, HitPoints, PhotonDeposits, RayBatch
from dosppm_core.modes.sppm import Progress, RenderSettings
from dosppm_core.sppm.statistics import PixelStatistics, initial_radius
from dosppm_core.trace import NO_CULL, emit_photon_job, eye_ray_job


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


def _release_freed_memory_to_the_os() -> None:
    """glibc raises its mmap threshold after big frees (up to 32 MiB), so
    evicted chunk arrays are kept in the heap for reuse and the process
    grows past its limit over a long render (measured: +17-35 MiB after
    12 iterations). A fixed 128 KiB threshold serves every large array
    from mmap, returned on free. No-op off glibc."""
    import ctypes
    try:
        libc = ctypes.CDLL("libc.so.6")
        libc.mallopt(-3, 128 * 1024)   # M_MMAP_THRESHOLD
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
        return True

    def activate(self, k: int) -> ChunkView:
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


class OutOfCoreRenderer:
    """Drives OSPPM iterations over a chunked scene in this process.

    `memory_bytes` limits resident chunk geometry (estimated as the store
    does, BVH included); default: room for every chunk.

    Two schedules:
    - `pipelined=False` (the paper's §3.1 OSPPM): an iteration drains its eye
      paths, then its photons, through every chunk until all have ended.
      Each iteration then sees exactly the photons of a single-process
      iteration, so the image equals `render.Renderer`'s.
    - `pipelined=True` (default; §3.3): an iteration is one sweep over
      the chunks, each activated at most once, tracing whatever eye and
      photon rays wait for it. Rays that cross back to a chunk already
      swept wait in its queue for the next iteration, beside new photons,
      instead of the sweep repeating for a thinning tail; an eye iteration
      replaces the hit points once its last path has ended. Photons count
      as emitted when emitted, so an image is short by the photons still
      in queues (under one iteration's worth); `finish()` drains them.
    """

    def __init__(self, provider, settings: RenderSettings | None = None,
                 memory_bytes: float | None = None, pipelined: bool = True):
        self.provider = provider
        self.header, self.tree = provider.header, provider.tree
        self.settings = settings or RenderSettings()
        self.settings.validate()
        self.pipelined = pipelined
        s, cam = self.settings, self.header.camera
        cost = np.asarray(provider.chunk_memory, np.float64)
        if memory_bytes is None:
            memory_bytes = float(cost.sum())
        if memory_bytes < cost.max():
            raise ValueError(f"memory limit {memory_bytes:.0f} B is below the largest chunk "
                             f"({cost.max():.0f} B)")
        _release_freed_memory_to_the_os()
        self.cache = ChunkCache(provider, memory_bytes, threads=s.threads)
        self.stats = PixelStatistics(int(cam.width), int(cam.height), s.radius, s.alpha)
        self.eps_abs = self.header.spawn_epsilon()
        self.iteration = 0
        self.eye_iterations = 0
        self.next_photon_job = 0
        self.path_ends = np.zeros(len(END_NAMES), np.int64)
        self.hit_point_total = 0
        self.seconds = 0.0
        self.phase_seconds = {"eye": 0.0, "photon": 0.0, "update": 0.0}
        self._cursor = 0
        c = self.tree.chunk_count
        self._eye_queues = [[] for _ in range(c)]
        self._photon_queues = [[] for _ in range(c)]
        self._eye_in_flight = False
        self._eye_parts: tuple[list, list, list] = ([], [], [])
        self._deposits: list[PhotonDeposits] = []
        self._emitted_unapplied = 0
        self._cull = NO_CULL

    # -- the loop --------------------------------------------------------
    def run_iteration(self) -> Progress:
        t0 = time.perf_counter()
        if not self.pipelined or not self.stats.has_radius:
            # The first hit points must exist before any photon can count.
            self._start_eye_iteration()
            self._sweep(until_empty=True)
            self._finish_eye_iteration()
        if self.pipelined:
            if not self._eye_in_flight:
                self._start_eye_iteration()
            self._emit_photons()
            self._sweep(until_empty=False)
            if self._eye_in_flight and not any(self._eye_queues):
                self._finish_eye_iteration()
        else:
            self._emit_photons()
            self._sweep(until_empty=True)
        self._apply()
        self.iteration += 1
        self.seconds += time.perf_counter() - t0
        return self.progress()

    def finish(self) -> None:
        """Trace every queued ray to its end and apply its photons, so the
        image holds every photon counted as emitted."""
        t0 = time.perf_counter()
        self._sweep(until_empty=True)
        if self._eye_in_flight:
            self._finish_eye_iteration()
        self._apply()
        self.seconds += time.perf_counter() - t0

    @property
    def rays_queued(self) -> int:
        return sum(len(b) for q in (self._eye_queues, self._photon_queues) for part in q for b in part)

    def progress(self) -> Progress:
        ends = {name: int(c) for name, c in zip(END_NAMES, self.path_ends) if name != "continues"}
        return Progress(self.iteration, self.stats.photons_emitted, self.hit_point_total,
                        self.seconds, ends)

    def image(self) -> np.ndarray:
        return self.stats.radiance().astype(np.float32)

    def close(self) -> None:
        self.cache.close()

    # -- eye iterations and photon emission ----------------------------------
    def _start_eye_iteration(self) -> None:
        s, cam = self.settings, self.header.camera
        n_pix = int(cam.width) * int(cam.height)
        for start in range(0, n_pix, s.tile_pixels):
            batch = eye_ray_job(self.header, s.seed, self.eye_iterations, start,
                                min(s.tile_pixels, n_pix - start))
            self._enqueue(self._eye_queues, batch)
        self._eye_in_flight = True

    def _finish_eye_iteration(self) -> None:
        hits, pix, rgb = self._eye_parts
        hp = HitPoints.concat(hits)
        self.hit_point_total += len(hp)
        if not self.stats.has_radius:
            self.stats.set_initial_radius(initial_radius(self.header, hp))
        self.stats.replace_hit_points(hp, (np.concatenate(pix) if pix else np.empty(0, np.int32),
                                           np.concatenate(rgb) if rgb else np.empty((0, 3), np.float32)))
        self._eye_parts = ([], [], [])
        self._eye_in_flight = False
        self.eye_iterations += 1

    def _emit_photons(self) -> None:
        """One iteration's photon jobs, culled against the current hit
        points' box (it travels with the photons in spirit: a photon is
        culled where it lands, by the box of its emission time)."""
        s = self.settings
        box = self.stats.gather_box() if s.cull else None
        self._cull = NO_CULL if box is None else box
        left = s.photons_per_iteration
        while left > 0:
            count = min(s.photons_per_job, left)
            self._enqueue(self._photon_queues, emit_photon_job(
                self.header, s.seed, self.next_photon_job, count, self.eps_abs))
            self.next_photon_job += 1
            left -= count
        self._emitted_unapplied += s.photons_per_iteration

    def _apply(self) -> None:
        """Server batching: update in batches of at most `photon_batch`
        deposits; the emitted count goes with the first batch."""
        t0 = time.perf_counter()
        s = self.settings
        deposits = PhotonDeposits.concat(self._deposits)
        emitted, self._deposits, self._emitted_unapplied = self._emitted_unapplied, [], 0
        for start in range(0, max(len(deposits), 1), s.photon_batch):
            part = deposits.slice(start, min(start + s.photon_batch, len(deposits)))
            self.stats.apply_photons(part, emitted if start == 0 else 0, self.header.materials,
                                     gather=s.gather, threads=s.threads, reorder=s.reorder,
                                     hash_options=s.hash_options)
        self.phase_seconds["update"] += time.perf_counter() - t0

    # -- chunk queues --------------------------------------------------------
    def _enqueue(self, queues, batch: RayBatch) -> None:
        routed, lost = start_chunks(self.tree, batch)
        self.path_ends[ESCAPED] += lost
        for k, b in routed.items():
            queues[k].append(b)

    def _has_work(self, k: int) -> bool:
        return bool(self._eye_queues[k] or self._photon_queues[k])

    def _next_chunk(self, after: int, stop: int | None = None) -> int | None:
        """The next chunk with work after `after` in round-robin order,
        not going past `stop` (exclusive of wrapping beyond it)."""
        c = self.tree.chunk_count
        for i in range(1, c + 1):
            k = (after + i) % c
            if self._has_work(k):
                return k
            if k == stop:
                return None
        return None

    def _sweep(self, until_empty: bool) -> None:
        """Activate chunks with work in round-robin order. One sweep visits
        each chunk at most once, ending at the chunk before the first one
        (`until_empty=False`); otherwise sweeps repeat until no queue
        holds a ray."""
        c = self.tree.chunk_count
        k = self._next_chunk(self._cursor - 1)
        last = None if k is None else (k - 1) % c
        while k is not None:
            view = self.cache.activate(k)
            ahead = self._next_chunk(k, None if until_empty else last)
            if ahead is not None and ahead != k:
                self.cache.prefetch(ahead, active=k)
            self._trace_chunk(view)
            del view    # an evicted chunk must not outlive its eviction
            self._cursor = k
            if not until_empty and k == last:
                break
            # Go on to the chunk being prefetched: it still has work, and
            # the chunks between may only have received some just now.
            k = ahead if ahead is not None else (self._next_chunk(k) if until_empty else None)

    def _trace_chunk(self, view) -> None:
        """Trace the chunk's whole eye and photon queues, each coalesced
        into one batch (client batching), and queue what leaves."""
        k, s = view.index, self.settings
        if self._eye_queues[k]:
            t0 = time.perf_counter()
            batch = RayBatch.concat(self._eye_queues[k])
            self._eye_queues[k] = []
            h, (p, e), ends, out = trace_eye_in_chunk(view, batch, s.max_depth)
            for part, x in zip(self._eye_parts, (h, p, e)):
                part.append(x)
            self._account(ends, out, self._eye_queues)
            self.phase_seconds["eye"] += time.perf_counter() - t0
        if self._photon_queues[k]:
            t0 = time.perf_counter()
            batch = RayBatch.concat(self._photon_queues[k])
            self._photon_queues[k] = []
            dep, ends, _culled, out = trace_photons_in_chunk(view, batch, self._cull, s.max_depth)
            self._deposits.append(dep)
            self._account(ends, out, self._photon_queues)
            self.phase_seconds["photon"] += time.perf_counter() - t0

    def _account(self, ends, outgoing, queues) -> None:
        self.path_ends += ends
        self.cache.counters.traced_batches += 1
        for j, parts in outgoing.items():
            queues[j].extend(parts)
            self.cache.counters.portal_rays += sum(len(b) for b in parts)
