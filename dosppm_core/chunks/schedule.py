"""Which chunk to trace next, and which of its rays (Günther & Grosch §3.1,
§4.3; issue 31).

One scheduler serves OSPPM in one process and every DOSPPM tracer. Ray
packages wait in one queue per chunk and kind: photons; eye rays and the
shadow rays of their hit points, per eye iteration. A step takes one
chunk's waiting packages of one kind, coalesced up to `step_rays` (client
batching: packages split at portals merge again).

Eye work goes ahead of photons. An eye pass is a few hops from chunk to
chunk (camera, surface, shadow ray), and the pixels get nothing until its
last path has ended; any order of photons is as good. Out of core, round
robin behind photon queues deep enough to hide the loads made each hop
wait a whole sweep: 3 eye iterations in 30 s on the 5M building against
68 with every chunk resident.

- Within a chunk, strictly: its eye rays (oldest iteration first), then
  their shadow rays, then photons, oldest job first (`take`).
- Between chunks, by waiting time: the next chunk is the one whose work
  has waited longest, eye work counting `EYE_PRIORITY` times its wait,
  but no chunk with work left unvisited more than `PHOTON_WAIT_DWELLS`
  dwells (`pick`). Photons wait from when this scheduler first saw their
  oldest job, so a job's stragglers are pursued from chunk to chunk: its
  last path decides when it counts. Strict priority here starved photons: the tracer holding the
  camera's chunk always had eye work somewhere, every photon job has
  photons in every chunk, and not one job completed in 20 s; weighted
  alone, a photon chunk of that tracer waited 22 s and more.
- When not every chunk fits, a chunk once activated keeps serving photons
  for `dwell_s` seconds (the paper's "load the next chunk when all its
  jobs are processed", without starving the others while work keeps
  coming): a load's cost over `pacing.LOAD_SHARE`, so loads stay that
  share of the time. It serves its eye work for as long as that lasts.

Photons go oldest job first: each package waits with the age of its
oldest job (its smallest job id; ids grow with emission). A photon job
counts only once its last path has ended, and a path crossing a portal
would otherwise queue behind every photon emitted since.

Items are any objects with a length in rays (a `RayBatch`, a tracer's
package with its credit): the scheduler only counts and orders them.
"""
from __future__ import annotations

import heapq
import itertools
import time
from collections import deque
from dataclasses import dataclass, field
from typing import Callable

DWELL_S = 1.0           # photons traced on one chunk before moving on, when not all fit (see `dwell_s`)
EYE_PRIORITY = 16.0     # eye work's wait counts this many times a photon's (`pick`)
PHOTON_WAIT_DWELLS = 3  # photons never wait more than this many dwells while eye work goes first
PHOTON, EYE, SHADOW = "photon", "eye", "shadow"


@dataclass
class ChunkQueue:
    photons: list = field(default_factory=list)      # a heap of (age, arrival, item)
    eye: dict = field(default_factory=dict)          # eye iteration -> deque of items
    shadows: dict = field(default_factory=dict)      # eye iteration -> deque of items
    rays: int = 0
    eye_rays: int = 0                                # of `rays`, eye and shadow rays
    eye_since: float | None = None   # eye work waiting since (None: active, or none waits)
    unvisited_since: float | None = None    # has had work, unvisited, since

    def __bool__(self) -> bool:
        return self.rays > 0

    def items(self):
        """(kind, eye iteration or None, item) of everything queued."""
        yield from ((PHOTON, None, p) for _age, _n, p in sorted(self.photons, key=lambda x: x[:2]))
        for kind, queues in ((EYE, self.eye), (SHADOW, self.shadows)):
            yield from ((kind, e, p) for e, ps in queues.items() for p in ps)


@dataclass
class Taken:
    """What a step traces: `items` of one kind (and eye iteration)."""
    kind: str
    eye_iteration: int | None
    items: list
    rays: int


class ChunkScheduler:
    """Queues per chunk and the choice of the next chunk and batch."""

    def __init__(self, chunk_count: int, step_rays: int, dwell_s: float = DWELL_S,
                 clock: Callable[[], float] = time.perf_counter):
        self.chunk_count, self.step_rays, self.dwell_s = int(chunk_count), int(step_rays), float(dwell_s)
        self.clock = clock
        self.queues: dict[int, ChunkQueue] = {}
        self.active: int | None = None
        self._until = 0.0                     # the active chunk serves photons until then
        self._arrivals = itertools.count()    # ties of age keep arrival order
        self._seen: dict[int, float] = {}     # photon job age -> when first queued here

    # -- queues ------------------------------------------------------------
    def push(self, chunk: int, kind: str, item, eye_iteration: int | None = None, age: int = 0) -> None:
        """Queue `item` for `chunk`; a photon package with the `age` of its
        oldest job (smaller: older)."""
        q = self.queues.setdefault(int(chunk), ChunkQueue())
        now = self.clock()
        if kind == PHOTON:
            heapq.heappush(q.photons, (int(age), next(self._arrivals), item))
            self._seen.setdefault(int(age), now)
        else:
            (q.shadows if kind == SHADOW else q.eye).setdefault(int(eye_iteration), deque()).append(item)
            q.eye_rays += len(item)
            q.eye_since = now if q.eye_since is None else q.eye_since
        if q.unvisited_since is None and chunk != self.active:
            q.unvisited_since = now
        q.rays += len(item)

    def pop(self, chunk: int) -> ChunkQueue | None:
        """Chunk's whole queue, taken out (another tracer serves it now)."""
        return self.queues.pop(chunk, None)

    def clear(self) -> None:
        self.queues.clear()
        self._seen.clear()
        self.active = None

    @property
    def rays(self) -> int:
        return sum(q.rays for q in self.queues.values())

    @property
    def eye_rays(self) -> int:
        return sum(q.eye_rays for q in self.queues.values())

    def waiting(self) -> list[list]:
        """[chunk, rays, eye rays, seconds waited, oldest photon age] per
        chunk with work (the status page; age: see `push`)."""
        now = self.clock()
        return [[k, q.rays, q.eye_rays, round(self._wait(q, now), 3), q.photons[0][0] if q.photons else None]
                for k, q in sorted(self.queues.items()) if q]

    def has_work(self, k: int | None = None) -> bool:
        if k is None:
            return any(self.queues.values())
        return bool(self.queues.get(k))

    # -- the next chunk ------------------------------------------------------
    def pick(self, all_fit: bool, exclude=(), loading: int | None = None) -> int | None:
        """The chunk to trace next: the active one while it has eye work,
        or photons and its dwell lasts (only when not all chunks fit); else
        `loading` (the chunk being loaded ahead) if it has work, so no load
        is wasted; else the one whose work has waited longest (`_wait`),
        round robin among equals. Never one in `exclude` (OSPPM's chunks
        already swept)."""
        a, now = self.active, self.clock()
        q = self.queues.get(a) if a is not None else None
        if q and a not in exclude and (q.eye_rays or (now < self._until and not all_fit)):
            return a
        if loading is not None and loading != a and loading not in exclude and self.has_work(loading):
            k = loading
        else:
            k = self._longest_waiting(now, after=-1 if a is None else a, skip=exclude)
        if q and k != a:                  # left with work: it waits from now
            q.unvisited_since = now
            if q.eye_rays:
                q.eye_since = now if q.eye_since is None else min(q.eye_since, now)
        if k is not None:                 # a visit begins
            self.queues[k].eye_since = self.queues[k].unvisited_since = None
            self._until = now + self.dwell_s
        self.active = k
        return k

    def _longest_waiting(self, now: float, after: int, skip=()) -> int | None:
        best, best_wait = None, -1.0
        for i in range(1, self.chunk_count + 1):
            k = (after + i) % self.chunk_count
            q = self.queues.get(k)
            if not q or k in skip:
                continue
            w = self._wait(q, now)
            if w > best_wait:
                best, best_wait = k, w
        return best

    def _wait(self, q: ChunkQueue, now: float) -> float:
        """How long its work has waited, eye work's weighted; a chunk left
        unvisited past PHOTON_WAIT_DWELLS dwells goes before any other."""
        w = now - self._seen.get(q.photons[0][0], now) if q.photons else 0.0
        if q.unvisited_since is not None and now - q.unvisited_since > PHOTON_WAIT_DWELLS * self.dwell_s:
            return now - q.unvisited_since + 1e9
        if q.eye_since is not None and q.eye_rays:
            w = max(w, EYE_PRIORITY * (now - q.eye_since))
        return w

    def ahead(self, k: int, exclude=()) -> int | None:
        """The chunk to load in the background while `k` traces: the one
        `pick` would choose next, were k done."""
        return self._longest_waiting(self.clock(), after=k, skip={k, *exclude})

    def eye_iterations_queued(self) -> set[int]:
        """Eye iterations with eye or shadow rays still queued."""
        return {e for q in self.queues.values() for queues in (q.eye, q.shadows) for e, ps in queues.items() if ps}

    # -- the next batch ------------------------------------------------------
    def take(self, k: int, photon_rays: int | None = None) -> Taken:
        """Chunk k's next batch: its oldest eye iteration's eye rays, else
        their shadow rays, else photons; packages coalesced up to
        `step_rays` (`photon_rays` for photons, if given), one at least.
        step_rays 0 takes one package."""
        q = self.queues[k]
        if q.eye or q.shadows:
            kind, queues = (EYE, q.eye) if q.eye else (SHADOW, q.shadows)
            e = min(queues)
            items = self._coalesce(queues[e], self.step_rays, deque.popleft)
            if not queues[e]:
                del queues[e]
            rays = sum(len(x) for x in items)
            q.eye_rays -= rays
        else:
            kind, e = PHOTON, None
            items = self._coalesce(q.photons, self.step_rays if photon_rays is None else photon_rays,
                                   lambda h: heapq.heappop(h)[2], lambda h: h[0][2])
            rays = sum(len(x) for x in items)
            self._forget_seen()
        q.rays -= rays
        if not q:
            del self.queues[k]
        return Taken(kind, e, items, rays)

    def _forget_seen(self) -> None:
        """Drop the first-seen times of jobs no longer queued here, now and
        then (a job seen again later counts from then)."""
        if len(self._seen) < 4096 or len(self._seen) < 2 * sum(len(q.photons) for q in self.queues.values()):
            return
        ages = {a for q in self.queues.values() for a, _n, _x in q.photons}
        self._seen = {a: t for a, t in self._seen.items() if a in ages}

    @staticmethod
    def _coalesce(items, limit: int, pop, first=lambda q: q[0]) -> list:
        """Items from the front of a queue (`pop`, `first`: its front) up to
        `limit` rays, one at least."""
        taken, rays = [], 0
        while items and (not taken or rays + len(first(items)) <= limit):
            taken.append(pop(items))
            rays += len(taken[-1])
        return taken
