"""OSPPM: out-of-core SPPM in one process (Günther & Grosch §3.1).

The scene lives in chunks (a chunk store on disk, or any object with
`header`, `tree`, `chunk_memory` and `load(k)`). Ray batches wait in the
library's chunk scheduler (`chunks/schedule.py`), the one every DOSPPM
tracer uses: eye work first, photons oldest job first. Chunks are
activated one after another in its order, with at most as many resident
as the memory limit allows; the next is loaded on a background thread
while the active one traces. A chunk's queued batches are coalesced
(client batching, §4.3), so packages that split at portals merge again
instead of multiplying.

An iteration is an eye phase (hit points of every pixel) and a photon
phase, then the statistics update, exactly as in `modes.sppm.Renderer` (both drive `sppm.iteration`); the
kernels, job records and statistics are the same, so the same seed gives
the same image whatever the number of chunks, up to floating-point noise.
"""
from __future__ import annotations

import time

import numpy as np

from dosppm_core.chunks import pacing
from dosppm_core.chunks.cache import ChunkCache
from dosppm_core.malloc import return_large_blocks
from dosppm_core.chunks.schedule import EYE, PHOTON, SHADOW, ChunkScheduler
from dosppm_core.chunks.view import (start_eye_paths, trace_eye_in_chunk, trace_photons_in_chunk,
                                     trace_shadows_in_chunk)
from dosppm_core.jobs import ESCAPED, HitPoints, PhotonDeposits, RayBatch, ShadowRays
from dosppm_core.kernels.light_cache import LightCache, share_of_memory
from dosppm_core.modes.deadline import Deadline, Rate, that_fit
from dosppm_core.settings import Progress, RenderSettings
from dosppm_core.sppm.iteration import EyePass, SPPMStatistics
from dosppm_core.trace import NO_CULL, emit_photon_job, environment, eye_ray_job, freeze_light_cache, light_arrays


TRACE_STEP_RAYS = 262_144      # photon rays traced at once in a chunk, at most (client batching up to this)
# With a deadline, besides the last update: a chunk's load or step that
# began just before the cut, and the image written.
FINISH_S = 0.8


class OutOfCoreRenderer:
    """Drives OSPPM iterations over a chunked scene in this process.

    `memory_bytes` limits resident chunk geometry (estimated as the store
    does, BVH included); default: room for every chunk.

    Two schedules:
    - `pipelined=False` (the paper's §3.1 OSPPM): an iteration drains its eye
      paths, then its photons, through every chunk until all have ended.
      Each iteration then sees exactly the photons of a single-process
      iteration, so the image equals `modes.sppm.Renderer`'s.
    - `pipelined=True` (default; §3.3): an iteration is one sweep over
      the chunks, each activated at most once, tracing whatever eye and
      photon rays wait for it. Rays that cross back to a chunk already
      swept wait in its queue for the next iteration, beside new photons,
      instead of the sweep repeating for a thinning tail. Each iteration
      starts an eye iteration while fewer than `eye_in_flight` are traced
      (out of core one sweep then serves several); they replace the hit
      points in order, each once its last path has ended. Photons count
      as emitted when emitted, so an image is short by the photons still
      in queues (under one iteration's worth); `finish()` drains them.

    With a deadline (`--time`, modes/deadline.py) an iteration emits only
    the photons its measured rate traces before it, emission stops when
    what is queued would take past it to drain, and `finish()` drains
    until only the time to finish is left of the grace: rays still queued
    then are dropped and counted (`paths_cut`), an eye iteration in flight
    too. Their photons' deposits so far are applied, so a render that must
    cut (its drain estimate was short) is dark by their remaining bounces.
    """

    def __init__(self, provider, settings: RenderSettings | None = None,
                 memory_bytes: float | None = None, pipelined: bool = True,
                 queue_memory_bytes: float | None = None):
        self.provider = provider
        self.header, self.tree = provider.header, provider.tree
        cam = provider.header.camera
        settings = settings or RenderSettings()
        # Photons per iteration not given: grown while chunk loads are not
        # hidden by the sweep's tracing (`_pace`), within the queue memory.
        self.paced = settings.photons_per_iteration is None and pipelined
        # Every photon of an iteration is queued at its start: half the
        # limit for the rays; a quarter for a batch of deposits waiting, a
        # quarter for the update's temporaries.
        self.max_photons_per_iteration = pacing.queue_cap_rays(queue_memory_bytes) // 2
        self.settings = settings.for_image(cam.width * cam.height)
        self.settings.photon_batch = min(self.settings.photon_batch, pacing.deposit_batch_cap(queue_memory_bytes))
        # A step's rays, the rays leaving it and its deposits: an eighth of the limit each, at most.
        self.trace_step_rays = min(TRACE_STEP_RAYS, max(1, pacing.queue_cap_rays(queue_memory_bytes) // 8))
        self.settings.validate()
        self.pipelined = pipelined
        s = self.settings
        cache_bytes = self._open_chunk_cache(memory_bytes)
        # An eye iteration per this many photons, whatever pacing makes of
        # an iteration's photons: the server's rule too.
        self.photons_per_eye_iteration = s.photons_per_iteration
        self._photons_since_eye = 0
        if self.paced:      # chunks will be loaded every sweep: start at a quarter of the limit
            s.photons_per_iteration = max(s.photons_per_iteration, self.max_photons_per_iteration // 4)
        self.sppm = SPPMStatistics(self.header, s)
        self.eps_abs = self.header.spawn_epsilon()
        self.lights = light_arrays(self.header.lights, LightCache(self.header.bounds, cache_bytes, frozen=True)) \
            if s.direct == "nee" else None
        self.env = environment(self.header.lights)
        self.iteration = 0
        self.eye_iterations = 0                   # installed
        self.next_photon_job = 0
        self.seconds = 0.0
        self.phase_seconds = {"eye": 0.0, "photon": 0.0, "update": 0.0}
        # The scheduler's clock is the work done (a second per million rays
        # traced), not the wall's: the order of chunks, and so the image,
        # repeats exactly from run to run.
        self.schedule = ChunkScheduler(self.tree.chunk_count, self.trace_step_rays,
                                       clock=lambda: self._rays_traced * 1e-6)
        self.eye_in_flight = pacing.eye_iterations_in_flight(
            int(cam.width) * int(cam.height),
            pacing.default_queue_memory() if queue_memory_bytes is None else queue_memory_bytes) if pipelined else 1
        self._eyes: dict[int, EyePass] = {}      # eye iterations in flight, by index
        self._eyes_started = 0
        self._emitted_unapplied = 0
        self._cull = NO_CULL
        self._deadline: Deadline | None = None
        self.photon_rate = Rate()          # photons emitted per second of iteration
        self.ray_rate = Rate()             # rays traced per second of sweep, chunk loads included
        self.paths_cut = 0                 # rays dropped at a deadline
        self._rays_traced = 0

    def _open_chunk_cache(self, memory_bytes: float | None) -> int:
        """The chunk cache within `memory_bytes` (default: every chunk), the
        light cache's share taken from it; returns that share."""
        s, cost = self.settings, np.asarray(self.provider.chunk_memory, np.float64)
        cache_bytes = s.light_cache
        if memory_bytes is None:
            memory_bytes = float(cost.sum())
        else:
            memory_bytes, cache_bytes = share_of_memory(memory_bytes, cost.max(initial=0.0), s.light_cache)
        if memory_bytes < cost.max():
            raise ValueError(f"memory limit {memory_bytes:.0f} B is below the largest chunk "
                             f"({cost.max():.0f} B)")
        return_large_blocks(replace=False)      # dosppm_core/malloc.py
        self.cache = ChunkCache(self.provider, memory_bytes, threads=s.threads)
        self.paced = self.paced and memory_bytes < cost.sum()     # all resident: nothing to hide
        return cache_bytes

    @property
    def stats(self):
        return self.sppm.stats

    @property
    def hit_point_total(self) -> int:
        return self.sppm.hit_point_total

    # -- the loop --------------------------------------------------------
    def worth_an_iteration(self, deadline: Deadline | None) -> bool:
        """Always the first; then while the deadline has not passed and
        what is queued drains before it (the iteration's photons are sized
        to the time left)."""
        if deadline is None or self.iteration == 0:
            return True
        return deadline.left() > self._drain_estimate_s()

    def _drain_estimate_s(self) -> float:
        r = self.ray_rate.per_s
        return self.rays_queued / r if r else 0.0

    def run_iteration(self, deadline: Deadline | None = None) -> Progress:
        """One iteration; with a `deadline`, it emits only the photons that
        its rate traces before it, less the time the queues need to drain."""
        self._deadline = deadline
        t0 = time.perf_counter()
        emitted0, traced0 = self.sppm.photons_applied + self._emitted_unapplied, self._rays_traced
        if not self.pipelined or not self.sppm.has_hit_points:
            # The first hit points must exist before any photon can count.
            self._start_eye_iteration()
            self._sweep(until_empty=True)
            self._install_eye_iterations()
        if self.pipelined:
            self._emit_photons()
            self._start_eye_iterations()
            swept = self._sweep_paced()
            self._install_eye_iterations()
        else:
            self._emit_photons()
            self._sweep(until_empty=True)
        self._apply()
        self.iteration += 1
        took = time.perf_counter() - t0
        self.seconds += took
        self.photon_rate.add(self.sppm.photons_applied - emitted0, took)
        self.ray_rate.add(self._rays_traced - traced0, took)
        if self.pipelined:
            self._pace(*swept)
        return self.progress()

    def _sweep_paced(self) -> tuple[float, float]:
        """One pipelined sweep: (seconds loading chunks, seconds tracing)."""
        load0, trace0 = self.cache.counters.load_seconds, self.phase_seconds["eye"] + self.phase_seconds["photon"]
        self._sweep(until_empty=False)
        return (self.cache.counters.load_seconds - load0,
                self.phase_seconds["eye"] + self.phase_seconds["photon"] - trace0)

    def _pace(self, load_s: float, trace_s: float) -> None:
        """Grow the photons per iteration (not set by the user) until the
        sweep's chunk loads are at most pacing.LOAD_SHARE of its time."""
        if not self.paced:
            return
        s = self.settings
        want = pacing.work_to_hide_loads(load_s, trace_s, s.photons_per_iteration)
        s.photons_per_iteration = pacing.grown(s.photons_per_iteration, want,
                                               max(s.photons_per_iteration, self.max_photons_per_iteration),
                                               first=self.iteration == 1)

    def finish(self, report=None, deadline: Deadline | None = None) -> None:
        """Trace every queued ray to its end and apply its photons, so the
        image holds every photon counted as emitted. Out of core this takes
        sweeps, each loading the chunks with work: `report(rays still
        queued, sweeps so far)` after each one. With a `deadline`, only
        until the time to finish is all that is left of its grace."""
        self._deadline = deadline
        t0 = time.perf_counter()
        sweeps = 0
        while self.rays_queued and not self._out_of_time():
            self._sweep(until_empty=False)
            sweeps += 1
            if report is not None:
                report(self.rays_queued, sweeps)
        if self.rays_queued:
            self._cut()
        self._install_eye_iterations()
        self._apply()
        self.seconds += time.perf_counter() - t0

    def _out_of_time(self) -> bool:
        """Only the time to finish (the last update's pace and FINISH_S) is
        left of the deadline's grace."""
        d = self._deadline
        update = self.sppm.update_seconds / max(1, self.sppm.updates)
        return d is not None and d.hard_left() <= min(d.grace, FINISH_S + 2 * update)

    def _cut(self) -> None:
        """At the deadline: the rays still queued are dropped and counted,
        and the eye iterations in flight with them (the hit points stay the
        last complete iteration's)."""
        self.paths_cut += self.schedule.rays - self.schedule.eye_rays
        self.schedule.clear()
        self._eyes.clear()

    @property
    def rays_queued(self) -> int:
        return self.schedule.rays

    def progress(self) -> Progress:
        return self.sppm.progress(self.iteration, self.seconds)

    def image(self) -> np.ndarray:
        return self.sppm.image()

    def close(self) -> None:
        self.cache.close()

    # -- eye iterations and photon emission ----------------------------------
    def _start_eye_iteration(self) -> None:
        s, cam = self.settings, self.header.camera
        n_pix = int(cam.width) * int(cam.height)
        e = self._eyes_started
        self._eyes_started += 1
        self._eyes[e] = EyePass(e)
        for start in range(0, n_pix, s.tile_pixels):
            batch = eye_ray_job(self.header, s.seed, e, start, min(s.tile_pixels, n_pix - start))
            self._enqueue(EYE, batch, e)
        freeze_light_cache(self.lights)

    def _start_eye_iterations(self) -> None:
        """An eye iteration for each `photons_per_eye_iteration` photons
        emitted since the last began, while fewer than `eye_in_flight` are
        traced; one at least when none is. Paced out of core an iteration
        emits millions of photons (to hide its loads), and one eye
        iteration per iteration left the pixels 3 eye samples in 30 s on
        the 5M building."""
        per = max(1, self.photons_per_eye_iteration)
        while len(self._eyes) < self.eye_in_flight and (not self._eyes or self._photons_since_eye >= per):
            self._start_eye_iteration()
            self._photons_since_eye = max(0, self._photons_since_eye - per)
        self._photons_since_eye = min(self._photons_since_eye, per * self.eye_in_flight)

    def _install_eye_iterations(self) -> None:
        """Eye iterations whose paths have all ended replace the hit points,
        in order: a later one waits for the earlier ones."""
        queued = self.schedule.eye_iterations_queued()
        while self._eyes and min(self._eyes) not in queued:
            self.sppm.install_eye_pass(self._eyes.pop(min(self._eyes)))
            self.eye_iterations += 1

    def _emit_photons(self) -> None:
        """One iteration's photon jobs, culled against the current hit
        points' box (it travels with the photons in spirit: a photon is
        culled where it lands, by the box of its emission time)."""
        s = self.settings
        self._cull = self.sppm.cull_box()
        emitted = left = self._photons_fitting(self._photons_to_emit())
        self._photons_since_eye += emitted
        while left > 0:
            count = min(s.photons_per_job, left)
            self._enqueue(PHOTON, emit_photon_job(self.header, s.seed, self.next_photon_job, count, self.eps_abs))
            self.next_photon_job += 1
            left -= count
        self._emitted_unapplied += emitted

    def _photons_fitting(self, wanted: int) -> int:
        """With a deadline: as many as the iteration rate traces in the time
        left once the queues have drained (none once that is past)."""
        d = self._deadline
        left = None if d is None else d.left() - self._drain_estimate_s()
        return that_fit(left, wanted, self.photon_rate.per_s, self.settings.photons_per_job)

    def _photons_to_emit(self) -> int:
        """The photons per iteration; paced, only as many as fit beside the
        rays carried over from earlier sweeps, so the queues stay within
        their half of --queue-memory (a job's worth at least). Carried-over
        rays beside a full iteration took OSPPM to 412 MiB against a 400 MiB
        limit at 119 chunks, in runs that reached a third iteration."""
        s = self.settings
        if not self.paced:
            return s.photons_per_iteration
        room = self.max_photons_per_iteration - self.rays_queued
        return min(s.photons_per_iteration, max(room, s.photons_per_job))

    def _apply(self) -> None:
        """The deposits still waiting, applied; the photons emitted this
        iteration count with them. Most were applied during the sweep, a
        batch at a time (`_add_deposits`)."""
        t0 = time.perf_counter()
        emitted, self._emitted_unapplied = self._emitted_unapplied, 0
        self.sppm.add_photons(PhotonDeposits.empty(), emitted)
        self.sppm.flush()
        self.phase_seconds["update"] += time.perf_counter() - t0

    def _add_deposits(self, deposits: PhotonDeposits) -> None:
        """A chunk's deposits, applied each time `photon_batch` wait: a
        paced iteration's deposits would otherwise all wait for its end
        (issue 17: 491 MiB against a 400 MiB limit at 119 chunks)."""
        t0 = time.perf_counter()
        self.sppm.add_photons(deposits, 0)
        self.phase_seconds["update"] += time.perf_counter() - t0

    # -- chunk queues --------------------------------------------------------
    def _enqueue(self, kind: str, batch: RayBatch, eye_iteration: int | None = None) -> None:
        routed, lost, seen = start_eye_paths(self.tree, batch, self.env if kind == EYE else None)
        self.sppm.path_ends[ESCAPED] += lost
        if len(seen[0]):        # eye rays that miss the scene see the environment
            self._eyes[eye_iteration].add(HitPoints.empty(), *seen)
        for k, b in routed.items():
            self._push(kind, k, b, eye_iteration)

    def _push(self, kind: str, k: int, batch, eye_iteration: int | None = None) -> None:
        age = int(batch.job.min()) if kind == PHOTON else 0
        self.schedule.push(k, kind, batch, eye_iteration, age=age)

    def _sweep(self, until_empty: bool) -> None:
        """Activate chunks with work in the scheduler's order, tracing each
        one's queue until it is empty ("load the next chunk when all its
        jobs are processed"). One sweep visits each chunk at most once
        (`until_empty=False`); otherwise visits go on until no queue holds
        a ray."""
        swept: set[int] = set()
        while not self._out_of_time():
            k = self.schedule.pick(True, exclude=() if until_empty else swept, loading=self.cache.loading)
            if k is None:
                return
            swept.add(k)
            view = self.cache.activate(k, self.schedule.ahead(k, exclude=() if until_empty else swept))
            while self.schedule.has_work(k) and not self._out_of_time():
                self._step(view, k)
            del view    # an evicted chunk must not outlive its eviction

    def _step(self, view, k: int) -> None:
        """Trace the chunk's next batch (eye rays, their shadow rays, or up
        to `trace_step_rays` photons: a photon iteration starts all in the
        chunks with lights, and one concatenation of it all, with the rays
        leaving it, would take three times the queue's memory at once) and
        queue what leaves it."""
        s, t0 = self.settings, time.perf_counter()
        taken = self.schedule.take(k, photon_rays=self.trace_step_rays)
        self._rays_traced += taken.rays
        if taken.kind == EYE:
            hits, (pixels, rgb), ends, out, shadows = trace_eye_in_chunk(
                view, RayBatch.concat(taken.items), s.max_depth, self.lights)
            self._eyes[taken.eye_iteration].add(hits, pixels, rgb)
            self._account(ends, EYE, out, taken.eye_iteration)
            self._account(np.zeros_like(ends), SHADOW, shadows, taken.eye_iteration)
        elif taken.kind == SHADOW:
            (pixels, rgb), ends, out = trace_shadows_in_chunk(view, ShadowRays.concat(taken.items))
            self._eyes[taken.eye_iteration].add(HitPoints.empty(), pixels, rgb)
            self._account(ends, SHADOW, {j: [part] for j, part in out.items()}, taken.eye_iteration)
        else:
            dep, ends, _culled, out = trace_photons_in_chunk(view, RayBatch.concat(taken.items), self._cull,
                                                             s.max_depth, s.deposit_from, self.lights)
            self._account(ends, PHOTON, out)
            self.phase_seconds["photon"] += time.perf_counter() - t0
            self._add_deposits(dep)
            return
        self.phase_seconds["eye"] += time.perf_counter() - t0

    def _account(self, ends, kind: str, outgoing, eye_iteration: int | None = None) -> None:
        self.sppm.count_path_ends(ends)
        self.cache.counters.traced_batches += 1
        for j, parts in outgoing.items():
            for b in parts:
                self._push(kind, j, b, eye_iteration)
            self.cache.counters.portal_rays += sum(len(b) for b in parts)
