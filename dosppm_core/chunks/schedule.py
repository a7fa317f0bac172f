"""Which chunk to trace next, and which of its rays (Günther & Grosch §3.1,
§4.3; issue 31).

One scheduler serves OSPPM in one process and every DOSPPM tracer. Ray
packages wait in one queue per chunk and kind: photons; eye rays and the
shadow rays of their hit points, per eye iteration. A step takes one
chunk's waiting packages of one kind, coalesced up to `step_rays` (client
batching: packages split at portals merge again).

Eye work goes first, in the choice of chunk and within a chunk. An eye
pass is a few hops from chunk to chunk (camera, surface, shadow ray), and
the pixels get nothing until its last path has ended; photons are many
and any order of them is as good. Out of core, round robin with photon
queues deep enough to hide the loads made each hop wait a whole sweep: 4
eye iterations in 30 s on the 5M building against 41 with every chunk
resident. So a chunk that eye rays wait for is activated (and prefetched)
before one that only photons wait for, and the active chunk keeps serving
photons for at most `dwell_s` seconds when not all chunks fit (the
paper's "load the next chunk when all its jobs are processed", without
starving the others while work keeps coming). The dwell is what a chunk
load costs over `pacing.LOAD_SHARE`, so loads stay that share of the time
while a photon crossing a portal waits at most a sweep of dwells: 32 steps
of 65k rays, as it was, held a chunk for about 4 s, and a path's every
crossing waited up to 16 s behind four chunks.

Photons go oldest first: each package waits with the age of its oldest
job (its smallest job id; ids grow with emission), and a chunk traces the
oldest photons it holds. A photon job counts only once its last path has
ended, and a path crossing a portal used to queue behind every photon
emitted since: on the 5M building out of core not one job of 8.6M photons
completed before the drain. Oldest first, a job's stragglers overtake
newer photons at every chunk they reach.

Items are any objects with a length in rays (a `RayBatch`, a tracer's
package with its credit): the scheduler only counts and orders them.
"""
from __future__ import annotations

import heapq
import itertools
from collections import deque
from dataclasses import dataclass, field

DWELL_S = 1.0           # photons traced on one chunk before moving on, when not all fit (see `dwell_s`)
PHOTON, EYE, SHADOW = "photon", "eye", "shadow"


def next_with_work(has_work, after: int, chunk_count: int, stop: int | None = None) -> int | None:
    """The next chunk with work after `after` in round-robin order (`after`
    itself last), or None; with `stop`, not going past that chunk."""
    for i in range(1, chunk_count + 1):
        k = (after + i) % chunk_count
        if has_work(k):
            return k
        if k == stop:
            return None
    return None


@dataclass
class ChunkQueue:
    photons: list = field(default_factory=list)      # a heap of (age, arrival, item)
    eye: dict = field(default_factory=dict)          # eye iteration -> deque of items
    shadows: dict = field(default_factory=dict)      # eye iteration -> deque of items
    rays: int = 0
    eye_rays: int = 0                                # of `rays`, eye and shadow rays

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

    def __init__(self, chunk_count: int, step_rays: int, dwell_s: float = DWELL_S):
        self.chunk_count, self.step_rays, self.dwell_s = int(chunk_count), int(step_rays), float(dwell_s)
        self.queues: dict[int, ChunkQueue] = {}
        self.active: int | None = None
        self._since = 0.0                     # when the active chunk was picked
        self._arrivals = itertools.count()    # ties of age keep arrival order

    # -- queues ------------------------------------------------------------
    def push(self, chunk: int, kind: str, item, eye_iteration: int | None = None, age: int = 0) -> None:
        """Queue `item` for `chunk`; a photon package with the `age` of its
        oldest job (smaller: older)."""
        q = self.queues.setdefault(int(chunk), ChunkQueue())
        if kind == PHOTON:
            heapq.heappush(q.photons, (int(age), next(self._arrivals), item))
        else:
            (q.shadows if kind == SHADOW else q.eye).setdefault(int(eye_iteration), deque()).append(item)
            q.eye_rays += len(item)
        q.rays += len(item)

    def pop(self, chunk: int) -> ChunkQueue | None:
        """Chunk's whole queue, taken out (another tracer serves it now)."""
        return self.queues.pop(chunk, None)

    def clear(self) -> None:
        self.queues.clear()
        self.active = None

    @property
    def rays(self) -> int:
        return sum(q.rays for q in self.queues.values())

    @property
    def eye_rays(self) -> int:
        return sum(q.eye_rays for q in self.queues.values())

    def has_work(self, k: int | None = None) -> bool:
        if k is None:
            return any(self.queues.values())
        return bool(self.queues.get(k))

    def _has_eye_work(self, k: int) -> bool:
        q = self.queues.get(k)
        return q is not None and q.eye_rays > 0

    # -- the next chunk ------------------------------------------------------
    def pick(self, all_fit: bool, now: float) -> int | None:
        """The chunk to trace next at time `now` (seconds): the active one
        while it has eye work, else the next with eye work round robin; with
        none, the active one until it has been active `dwell_s` when not all
        chunks fit, else the next with work."""
        a = self.active
        after = -1 if a is None else a
        if any(q.eye_rays for q in self.queues.values()):
            k = a if self._has_eye_work(a) else next_with_work(self._has_eye_work, after, self.chunk_count)
        elif a is not None and self.has_work(a) and now - self._since < self.dwell_s and not all_fit:
            k = a
        else:
            k = next_with_work(self.has_work, after, self.chunk_count)
        if k != a:
            self._since = now
        self.active = k
        return k

    def ahead(self, k: int) -> int | None:
        """The chunk to load in the background while `k` traces: the next
        one eye rays wait for, else the next with work."""
        if self.eye_rays - (self.queues[k].eye_rays if k in self.queues else 0) > 0:
            return next_with_work(self._has_eye_work, k, self.chunk_count, stop=None)
        return next_with_work(self.has_work, k, self.chunk_count)

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
        q.rays -= rays
        if not q:
            del self.queues[k]
        return Taken(kind, e, items, rays)

    @staticmethod
    def _coalesce(items, limit: int, pop, first=lambda q: q[0]) -> list:
        """Items from the front of a queue (`pop`, `first`: its front) up to
        `limit` rays, one at least."""
        taken, rays = [], 0
        while items and (not taken or rays + len(first(items)) <= limit):
            taken.append(pop(items))
            rays += len(taken[-1])
        return taken
