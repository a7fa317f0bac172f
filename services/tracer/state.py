"""The tracer's state (Günther & Grosch §3.1, §4.3), apart from its sockets.

A tracer owns some chunks. Ray packages for them (eye jobs from the
server, photons it made, portal packages from other tracers) wait in the
library's chunk scheduler (`dosppm_core.chunks.schedule`, eye work
first), as OSPPM's do.
A step activates the chunk it picks (loading it under the memory budget,
the next one prefetched), traces the batch it coalesces there with the
library's chunk kernels and returns the messages to send: `results` to the
server (ended paths per job, deposits, hit points, light reaching pixels)
and `portal_rays` for the chunks the rays enter next. An eye path that
stores a hit point goes on as its shadow ray (kind "shadow", same job),
which crosses portals like any ray and ends the path where it stops. Packages for a chunk this tracer does not
serve are passed on to a tracer that does.

Photon jobs come from the server as (id, rng key, count), eye jobs as
tiles (id, pixel start, count): the tracer makes their photons (`emit`)
or eye rays (`eye_tiles`) and sends them on as a step sends its rays,
with a `results` message for the emission (chunk None).

Nothing here opens a socket: `TracerState` takes decoded message fields
and returns `Out` records, so tests drive whole clusters of them in one
process, and the I/O shell (`tracer.py`) only moves frames.
"""
from __future__ import annotations

import itertools
import time
from dataclasses import dataclass

import numpy as np

from dosppm_core.chunks import pacing
from dosppm_core.chunks.cache import ChunkCache
from dosppm_core.chunks.schedule import EYE, PHOTON, SHADOW, ChunkScheduler
from dosppm_core.chunks.view import (located_photons, start_chunks, start_eye_paths, trace_eye_in_chunk,
                                     trace_photons_in_chunk, trace_shadows_in_chunk)
from dosppm_core.jobs import END_NAMES, ESCAPED, HitPoints, RayBatch, ShadowRays, paths_per_job
from dosppm_core.kernels.light_cache import LightCache, share_of_memory
from dosppm_core.settings import LIGHT_CACHE_BYTES
from dosppm_core.sppm.iteration import keeps_hit_points
from dosppm_core.trace import environment, eye_ray_job, light_arrays
from services.credit import split as split_credit
from services.wire import Out

_EPOCH_MESSAGES = ("hit_points", "gather", "drop_epoch")

SERVER = "server"           # Out.dest of messages for the server
STEP_RAYS = 65_536          # rays coalesced into one traced batch
_CARRY_CREDIT = ("photon_job", "eye_job", "portal_rays")


@dataclass
class Package:
    batch: RayBatch | ShadowRays
    credit: tuple                           # (job ids, exponents): its share of its jobs' credit
    cull_box: np.ndarray | None = None      # photons only

    def __len__(self) -> int:
        return len(self.batch)


def own_credit(batch) -> tuple:
    """Credit 1 for each job in `batch`: for packages made outside the
    protocol (the ledger's re-trace, tests), whose credit nobody sums."""
    ids = np.unique(batch.job)
    return ids.astype(np.int64), np.zeros(len(ids), np.int64)


def concat_credit(packages: list[Package]) -> tuple:
    return (np.concatenate([p.credit[0] for p in packages]),
            np.concatenate([p.credit[1] for p in packages]))


def union_box(boxes: list[np.ndarray]) -> np.ndarray:
    """The cull box of coalesced photon packages: the union of theirs
    ("expanded when tracing jobs are joined", §4.3), so no photon is culled
    by a box tighter than the one it was emitted with."""
    stack = np.stack(boxes)
    return np.stack([stack[:, 0].min(0), stack[:, 1].max(0)])


class TracerState:
    """Queues, chunk cache and routing of one tracer."""

    def __init__(self, endpoint: str, provider, max_depth: int, memory_bytes: float | None = None,
                 threads: int = 1, step_rays: int = STEP_RAYS, direct: str = "nee",
                 queue_memory_bytes: float | None = None, light_cache: int = LIGHT_CACHE_BYTES,
                 clock=time.perf_counter, seed: int | None = None, header=None, hit_point_stride: int = 1):
        """`clock`: seconds, for the scheduler's waits and dwells (a cluster
        in one process passes its own, so its runs repeat exactly).
        `seed`: the render's (the welcome's settings), which photon jobs'
        photons and eye tiles' rays are made from; None: this tracer takes
        no jobs. `header`: the render's scene header (the welcome's), whose
        camera the eye rays are made with: the store's may have another
        resolution (`--width`, `--height`); None: the provider's.
        `hit_point_stride`: the welcome's; eye iterations that install no
        hit points (`keeps_hit_points`) send none, only what they saw."""
        self.endpoint, self.provider, self.max_depth = endpoint, provider, int(max_depth)
        self.seed, self.hit_point_stride = seed, int(hit_point_stride)
        self.header = provider.header if header is None else header
        self.env = environment(self.header.lights)     # what eye rays missing the scene see
        # Direct light by shadow rays ('nee'): photons deposit from their
        # second surface on. 'photons': the paper's pure estimator.
        self.deposit_from = 1 if direct == "nee" else 0
        self.step_rays = int(step_rays)
        cost = np.asarray(provider.chunk_memory, np.float64)
        if memory_bytes is None:        # its share of the machine, at least one chunk
            memory_bytes = float(pacing.default_chunk_memory(at_least=cost.max(initial=0.0)))
        # The light cache this tracer learns for its chunks counts in its memory.
        memory_bytes, cache_bytes = share_of_memory(memory_bytes, cost.max(initial=0.0), light_cache)
        self.lights = light_arrays(provider.header.lights, LightCache(provider.header.bounds, cache_bytes)) \
            if direct == "nee" else None
        self.cache = ChunkCache(provider, memory_bytes, threads=threads)
        self.queue_cap = pacing.queue_cap_rays(queue_memory_bytes)
        self._queue_target, self._loads_at_pace = 0, 0
        self._paced_at: tuple[float, int] | None = None     # (time, rays traced) at the last pacing
        self.clock = clock
        self.schedule = ChunkScheduler(provider.tree.chunk_count, self.step_rays, clock=clock)
        # Per chunk, the endpoints of the tracers serving it (the server's
        # `owners` holds their ids): where portal packages go.
        self.peer_endpoints: list[list[str]] = [[] for _ in range(provider.tree.chunk_count)]
        self.table_version = -1
        self._next_owner = [itertools.count() for _ in self.peer_endpoints]
        # Portal packages for chunks no tracer serves yet (a table still
        # being built); retried when the next table arrives.
        self.unroutable: list = []
        self.counters = {"steps": 0, "rays_traced": 0, "photons_emitted": 0, "eye_rays_made": 0,
                         "photons_traced": 0, "portal_rays_out": 0, "portal_rays_in": 0, "forwarded_rays": 0,
                         "busy_s": 0.0}
        self.portal_by_chunk: dict[int, list[int]] = {}     # chunk -> [rays in, rays out] (status page)
        self.rays_by_chunk: dict[int, int] = {}             # chunk -> rays traced (the server balances by it)
        self.epochs = None      # EpochDeposits when the gather is at the tracers (`hold_epochs`)
        self.light = None       # LightHold when the server collects eye light in rounds (`hold_light`)

    # -- the peer table ----------------------------------------------------------
    def set_peers(self, table_version: int, owners: list[list[str]]) -> list[Out]:
        """Install the server's table of who serves each chunk; packages
        waiting for chunks this tracer no longer serves move on."""
        if table_version <= self.table_version:
            return []
        if len(owners) != len(self.peer_endpoints):
            raise ValueError(f"peer table lists {len(owners)} chunks, the scene has {len(self.peer_endpoints)}")
        self.peer_endpoints, self.table_version = [list(o) for o in owners], table_version
        out = []
        for k in [k for k in self.schedule.queues if not self.serves(k)]:
            out += self._hand_over(k)
        return out + self.retry_unroutable()

    def serves(self, chunk: int) -> bool:
        return self.endpoint in self.peer_endpoints[chunk]

    @property
    def chunks(self) -> list[int]:
        return [k for k, o in enumerate(self.peer_endpoints) if self.endpoint in o]

    def _hand_over(self, k: int) -> list[Out]:
        q = self.schedule.pop(k)
        out = [self._portal(k, kind, p.batch, p.credit, cull_box=p.cull_box, eye_iteration=e)
               for kind, e, p in q.items()]
        self.counters["forwarded_rays"] += q.rays
        return [o for o in out if o is not None]

    # -- incoming packages -------------------------------------------------------
    def receive(self, kind: str, chunk: int, batch: RayBatch | ShadowRays, cull_box=None,
                eye_iteration: int | None = None, credit: tuple | None = None) -> list[Out]:
        """Queue a package for `chunk` (an eye job, photons made here or a
        portal package) with its share of credit (None: `own_credit`), or
        pass it on when another tracer serves that chunk."""
        if not 0 <= chunk < len(self.peer_endpoints):
            raise ValueError(f"chunk {chunk} out of range (scene has {len(self.peer_endpoints)})")
        if not len(batch):
            return []
        credit = own_credit(batch) if credit is None else credit
        if not self.serves(chunk):
            self.counters["forwarded_rays"] += len(batch)
            out = self._portal(chunk, kind, batch, credit, cull_box=cull_box, eye_iteration=eye_iteration)
            return [] if out is None else [out]
        box = np.asarray(cull_box, np.float64) if kind == PHOTON else None
        age = int(batch.job.min()) if kind == PHOTON else 0
        self.schedule.push(chunk, kind, Package(batch, credit, box), eye_iteration, age=age)
        return []

    @property
    def provider_key(self) -> str | None:
        return getattr(self.provider, "key", None)

    def reset(self) -> None:
        """Forget every queued package (their jobs were discarded)."""
        self.schedule.clear()
        self.unroutable = []
        if self.epochs is not None:     # their epochs are discarded too (the server's _discard_epochs)
            self.epochs.clear()
        if self.light is not None:      # and the eye iterations whose light was held
            self.light.clear()

    def handle(self, msg) -> list[Out]:
        """A decoded message from the server or a peer."""
        if msg.type == "peers":
            return self.set_peers(msg.table_version, msg.peers)
        if msg.type in _EPOCH_MESSAGES:
            return self._epoch_message(msg)
        if msg.type == "light_request":
            if self.light is None:
                return [Out(SERVER, "error", dict(reason="light_request: this tracer holds no eye light",
                                                  about=msg.type))]
            return [Out(SERVER, "eye_light", self.light.reply(msg.round, msg.eye_iterations))]
        credit = (msg.credit_job, msg.credit_exp) if msg.type in _CARRY_CREDIT else None
        if msg.type == "photon_job":
            return self.emit(msg.job_ids, msg.rng_keys, msg.counts, msg.cull_box, credit)
        if msg.type == "eye_job":
            try:
                return self.eye_tiles(msg.eye_iteration, msg.job_ids, msg.pixel_starts, msg.counts, credit)
            except ValueError as e:     # a range only this tracer checks: refused whole, nothing made
                return [Out(SERVER, "error", dict(reason=f"eye_job: {e}", about="eye_job"))]
        if msg.type == "portal_rays":
            rays = msg.shadows if msg.kind == "shadow" else msg.batch
            self.counters["portal_rays_in"] += len(rays)
            self._count_portal(msg.chunk, len(rays), 0)
            return self.receive(msg.kind, msg.chunk, rays, cull_box=msg.cull_box,
                                eye_iteration=msg.eye_iteration, credit=credit)
        return []

    def hold_epochs(self, epochs) -> None:
        """Gather at the tracers: keep deposits by epoch (`epochs`, an
        `EpochDeposits`) instead of sending them with the results."""
        self.epochs = epochs

    def hold_light(self, hold) -> None:
        """Keep the light eye paths see (`hold`, a `LightHold`, or None to
        send it with the results) until the server asks for it."""
        self.light = hold

    def _epoch_message(self, msg) -> list[Out]:
        if self.epochs is None:
            return [Out(SERVER, "error", dict(reason=f"{msg.type}: this tracer gathers no epochs", about=msg.type))]
        if msg.type == "hit_points":
            self.epochs.set_hit_points(msg.hits_version, msg.hits)
            return []
        if msg.type == "drop_epoch":
            self.epochs.drop(msg.epoch)
            return []
        t0 = time.perf_counter()
        try:
            fields = self.epochs.reply(msg)
        except ValueError as e:
            return [Out(SERVER, "error", dict(reason=str(e), about="gather"))]
        self.epochs.counters["gather_s"] += time.perf_counter() - t0
        return [Out(SERVER, "epoch_sums", fields)]

    def emit(self, job_ids, rng_keys, counts, cull_box, credit: tuple) -> list[Out]:
        """Make the photons of a photon job message with the library's call
        (`located_photons`: the same seed and keys give bit for bit the same
        photons, whichever tracer makes them), and send them on as a step
        sends the rays leaving it: queued for chunks this tracer serves,
        portal packages for the others. Photons that miss the scene end
        here, escaped. Its results (chunk None) return the credit the
        packages do not carry."""
        if self.seed is None:
            raise ValueError("photon_job: this tracer was not given the render's seed")
        if not len(job_ids):
            return []
        tree = self.provider.tree
        batch, chunk = located_photons(self.provider.header, tree, self.seed, rng_keys, counts,
                                       self.provider.header.spawn_epsilon())
        batch.job[:] = np.repeat(np.asarray(job_ids, np.int64), counts)
        routed, lost = start_chunks(tree, batch, chunk=chunk)
        self.counters["photons_emitted"] += len(batch)
        ends = np.zeros(len(END_NAMES), np.int64)
        ends[ESCAPED] = lost
        return self._send_on(batch.job, credit, dict(chunk=None, ends=ends),
                             [(PHOTON, {k: [part] for k, part in routed.items()})],
                             cull_box=np.asarray(cull_box, np.float64))

    def eye_tiles(self, eye_iteration: int, job_ids, pixel_starts, counts, credit: tuple) -> list[Out]:
        """Make the eye rays of an eye_job's tiles with the library's call
        (`eye_ray_job`: the same seed, iteration and pixels give bit for bit
        the same rays, whichever tracer makes them) and send them on as
        `emit` sends photons: queued for chunks this tracer serves, portal
        packages for the others, and the rays that miss the scene ended
        here, escaped, in the results (chunk None) that return the credit
        the packages do not carry, with the environment light they see."""
        if self.seed is None:
            raise ValueError("this tracer was not given the render's seed")
        header = self.header
        n_pixels = int(header.camera.width) * int(header.camera.height)
        ends_at = np.asarray(pixel_starts, np.int64) + np.asarray(counts, np.int64)
        if len(ends_at) and ends_at.max() > n_pixels:
            raise ValueError(f"field 'pixel_starts' + 'counts' reaches pixel {int(ends_at.max())}, "
                             f"past the image's {n_pixels}")
        parts: dict[int, list[RayBatch]] = {}
        lost, jobs, seen = 0, [], []
        for j, start, count in zip(np.asarray(job_ids).tolist(), np.asarray(pixel_starts).tolist(),
                                   np.asarray(counts).tolist()):
            batch = eye_ray_job(header, self.seed, eye_iteration, start, count)
            batch.job[:] = j
            jobs.append(batch.job)
            routed, missed, light = start_eye_paths(self.provider.tree, batch, self.env)
            lost += missed
            seen.append(light)
            for k, part in routed.items():
                parts.setdefault(k, []).append(part)
        if not jobs:
            return []
        self.counters["eye_rays_made"] += int(np.sum(counts))
        ends = np.zeros(len(END_NAMES), np.int64)
        ends[ESCAPED] = lost
        fields = dict(chunk=None, ends=ends, eye_iteration=eye_iteration, hits=HitPoints.empty(),
                      emitted_pixels=np.concatenate([p for p, _ in seen]),
                      emitted_rgb=np.concatenate([rgb for _, rgb in seen]))
        return self._send_on(np.concatenate(jobs), credit, fields, [(EYE, parts)], eye_iteration=eye_iteration)

    @property
    def queued_rays(self) -> int:
        return self.schedule.rays

    def has_work(self) -> bool:
        return self.schedule.has_work()

    def all_fit(self) -> bool:
        return sum(self.cache.cost[k] for k in self.chunks) <= self.cache.memory

    def queue_target(self) -> int:
        """Rays this tracer asks the server to keep queued here (0: the
        server's default credit). See `_pace`."""
        return self._queue_target

    def _pace(self) -> None:
        """With more chunks than fit, every chunk is loaded again each
        sweep over them: each visit must find a dwell's worth of rays
        (`ChunkScheduler.dwell_s`, a load's cost over pacing.LOAD_SHARE),
        so the queue asks for a sweep of dwells at the tracing rate, but
        no more than the rays this tracer gets through, loads and eye work
        included, in pacing.LATENCY_S: each photon job waits for the queue
        ahead of it, and counts only once its last path has ended. Queues
        grown only to hide loads reached 4M rays, and jobs 27 s from
        emission to commit (issue 31). Re-measured after each sweep's worth
        of loads, within `queue_cap` (--queue-memory)."""
        cc = self.cache.counters
        if cc.loads:
            self.schedule.dwell_s = pacing.dwell_s(cc.load_seconds / cc.loads)
        if self.all_fit() or cc.loads - self._loads_at_pace < max(2, len(self.chunks)):
            return
        self._loads_at_pace = cc.loads
        now, rays = self.clock(), self.counters["rays_traced"]
        then = self._paced_at
        self._paced_at = (now, rays)
        if then is None:
            return                        # the first sweep: loads of a cold start, nothing to go by
        trace_s = self.counters["busy_s"] - cc.wait_seconds
        sweep = len(self.chunks) * self.schedule.dwell_s * rays / max(trace_s, 1e-9)
        through = (rays - then[1]) / max(now - then[0], 1e-9) * pacing.LATENCY_S
        self._queue_target = int(min(self.queue_cap, max(pacing.FIRST_QUEUE_RAYS, min(sweep, through))))

    # -- tracing -----------------------------------------------------------------
    def step(self) -> list[Out]:
        """Trace one coalesced batch in the chunk the scheduler picks; eye
        and shadow rays first (they gate the server's next eye iteration)."""
        k = self.schedule.pick(self.all_fit(), loading=self.cache.loading)
        if k is None:
            return []
        t0, rays = time.perf_counter(), self.counters["rays_traced"]
        view = self.cache.activate(k, ahead=self.schedule.ahead(k))
        taken = self.schedule.take(k)
        trace = {EYE: self._trace_eye, SHADOW: self._trace_shadows, PHOTON: self._trace_photons}[taken.kind]
        out = trace(view, taken)
        del view   # an evicted chunk must not outlive its eviction
        self.counters["steps"] += 1
        self.counters["busy_s"] += time.perf_counter() - t0
        self.rays_by_chunk[k] = self.rays_by_chunk.get(k, 0) + self.counters["rays_traced"] - rays
        self._pace()
        return out

    def _trace_eye(self, view, taken) -> list[Out]:
        e, batch = taken.eye_iteration, RayBatch.concat([p.batch for p in taken.items])
        hits, (pix, rgb), ends, outgoing, shadows = trace_eye_in_chunk(view, batch, self.max_depth,
                                                                       self.lights)
        made = len(hits)
        if not keeps_hit_points(e, self.hit_point_stride):
            hits = HitPoints.empty()
        fields = dict(chunk=view.index, eye_iteration=e, ends=ends, hits=hits, emitted_pixels=pix,
                      emitted_rgb=rgb, hit_points_made=made)
        return self._after_trace(batch, concat_credit(taken.items), fields,
                                 [(EYE, outgoing), (SHADOW, shadows)], eye_iteration=e)

    def _trace_shadows(self, view, taken) -> list[Out]:
        e, batch = taken.eye_iteration, ShadowRays.concat([p.batch for p in taken.items])
        (pix, rgb), ends, outgoing = trace_shadows_in_chunk(view, batch)
        fields = dict(chunk=view.index, eye_iteration=e, ends=ends, hits=HitPoints.empty(),
                      emitted_pixels=pix, emitted_rgb=rgb)
        outgoing = {k: [part] for k, part in outgoing.items()}
        return self._after_trace(batch, concat_credit(taken.items), fields, [(SHADOW, outgoing)],
                                 eye_iteration=e)

    def _trace_photons(self, view, taken) -> list[Out]:
        items = taken.items
        batch = RayBatch.concat([p.batch for p in items])
        self.counters["photons_traced"] += len(batch)
        box = union_box([p.cull_box for p in items])
        deposits, ends, culled, outgoing = trace_photons_in_chunk(view, batch, box, self.max_depth,
                                                                  self.deposit_from, self.lights)
        fields = dict(chunk=view.index, ends=ends, culled=int(culled), deposits=deposits)
        if self.epochs is not None:     # kept here until the server asks for the epoch's sums
            self.epochs.add(fields.pop("deposits"))
        return self._after_trace(batch, concat_credit(items), fields, [(PHOTON, outgoing)], cull_box=box)

    def _after_trace(self, batch, credit, fields, outgoing, **extra) -> list[Out]:
        """The step's results for the server and its packages leaving (`_send_on`)."""
        self.counters["rays_traced"] += len(batch)
        return self._send_on(batch.job, credit, fields, outgoing, **extra)

    def _send_on(self, job, credit, fields, outgoing, **extra) -> list[Out]:
        """The results of a step or an emission for the server, and its paths
        going on. `job`: the job column of the paths taken in, with their
        `credit`; `outgoing` is [(kind, {chunk: [records]})]: the paths
        going on, queued here for chunks this tracer serves and sent in
        portal packages for the others, whose job ids the results count as
        left. The credit is split between those packages and the results
        (services/credit.py), which return a share of every job they carry
        deposits or hit points of."""
        if self.light is not None and fields.get("emitted_pixels") is not None:
            self.light.add(fields["eye_iteration"], fields.pop("emitted_pixels"), fields.pop("emitted_rgb"))
        leaving = [(kind, chunk, type(parts[0]).concat(parts))
                   for kind, out in outgoing for chunk, parts in out.items()]
        fields["job_ids"], fields["job_fed"], fields["job_left"] = paths_per_job(
            [job], [b.job for _kind, _chunk, b in leaving])
        (fields["credit_job"], fields["credit_exp"]), shares = split_credit(
            *credit, [b.job for _kind, _chunk, b in leaving])
        portal = []
        for (kind, chunk, merged), share in zip(leaving, shares):
            if fields["chunk"] is not None:      # emitted photons were in no chunk before
                self._count_portal(fields["chunk"], 0, len(merged))
            if self.serves(chunk):
                self._count_portal(chunk, len(merged), 0)
                portal += self.receive(kind, chunk, merged, credit=share, **extra)
            else:
                self.counters["portal_rays_out"] += len(merged)
                o = self._portal(chunk, kind, merged, share, **extra)
                portal += [] if o is None else [o]
        fields["queued"], fields["queue_target"] = self.queued_rays, self.queue_target()
        return [Out(SERVER, "results", fields), *portal]

    def _portal(self, chunk: int, kind: str, batch: RayBatch, credit: tuple, cull_box=None,
                eye_iteration: int | None = None) -> Out | None:
        """A portal package to a tracer serving `chunk`, spreading packages
        over the tracers that share it (c < n). None while nobody serves it
        (the caller keeps it: see `unroutable`)."""
        owners = [o for o in self.peer_endpoints[chunk] if o != self.endpoint] or self.peer_endpoints[chunk]
        if not owners:
            self.unroutable.append((kind, chunk, batch, cull_box, eye_iteration, credit))
            return None
        dest = owners[next(self._next_owner[chunk]) % len(owners)]
        fields = dict(kind=kind, chunk=chunk, credit_job=credit[0], credit_exp=credit[1],
                      **{"shadows" if kind == "shadow" else "batch": batch})
        if kind == "photon":
            fields["cull_box"] = cull_box
        else:
            fields["eye_iteration"] = eye_iteration
        return Out(dest, "portal_rays", fields)

    def retry_unroutable(self) -> list[Out]:
        """Packages for chunks nobody served yet, now that the table may
        name an owner."""
        held, self.unroutable = self.unroutable, []
        out = []
        for kind, chunk, batch, box, e, credit in held:
            out += self.receive(kind, chunk, batch, cull_box=box, eye_iteration=e, credit=credit) \
                if self.serves(chunk) else [o for o in [self._portal(chunk, kind, batch, credit, box, e)] if o]
        return out

    def _count_portal(self, chunk: int, rays_in: int, rays_out: int) -> None:
        c = self.portal_by_chunk.setdefault(int(chunk), [0, 0])
        c[0] += rays_in
        c[1] += rays_out

    def status(self) -> dict:
        cc = self.cache.counters
        loads = {"chunk_loads": cc.loads, "load_s": round(cc.load_seconds, 3),
                 "load_wait_s": round(cc.wait_seconds, 3), "wasted_prefetches": cc.wasted_prefetches,
                 "queue_target": self.queue_target()}
        return {"queue": self.queued_rays, "chunks": self.chunks, **loads, "waiting": self.schedule.waiting(),
                "portal_by_chunk": [[k, i, o] for k, (i, o) in sorted(self.portal_by_chunk.items())],
                "rays_by_chunk": [[k, n] for k, n in sorted(self.rays_by_chunk.items())],
                "holds_every_chunk": bool(self.cache.cost.sum() <= self.cache.memory),
                "resident": sorted(self.cache.resident), **{k: (round(v, 3) if isinstance(v, float) else v)
                                                            for k, v in self.counters.items()},
                **({} if self.epochs is None else {"epochs": dict(self.epochs.counters, held=self.epochs.rows)})}

    def close(self) -> None:
        self.cache.close()
