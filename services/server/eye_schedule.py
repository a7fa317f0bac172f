"""`ServerState`'s eye iterations: each is split into tiles (§5.6), sent
as (job id, pixel start, count) to the least loaded tracer serving the
chunk the tile's rays start in, which makes the rays (`TracerState.eye_tiles`),
with up to `eye_in_flight` iterations traced at once; a complete one hands
its hit points over. A mixin of services/server/state.py.
"""
from __future__ import annotations

import numpy as np

from dosppm_core.sppm.iteration import keeps_hit_points

from services.server.records import EyeIteration, TracerInfo, Update
from services.wire import Out

# Eye rays one eye_job asks a tracer to make (56 B each at the tracer):
# an iteration's tiles go out in several messages, so no tracer makes a
# whole large image's rays in one call, and tiles spread as loads grow.
EYE_RAYS_PER_MESSAGE = 1 << 18


class EyeScheduleMixin:
    def _maybe_start_eye_iteration(self) -> list[Out]:
        s = self.settings
        if len(self.eyes) >= self.eye_in_flight or (
                self.eye_started and not self._eye_restart and
                self.counters["photons_emitted"] - self._photons_at_eye_start < s.photons_per_iteration):
            return []
        self._eye_restart = False
        self.eye_started = self._next_eye_index()
        e = EyeIteration(self.eye_started, 0)
        self.eyes[e.index], self.eye_started = e, self.eye_started + 1
        self._photons_at_eye_start = self.counters["photons_emitted"]
        tiles = [(start, min(s.tile_pixels, self.n_pixels - start))
                 for start in range(0, self.n_pixels, s.tile_pixels)]
        # Every tile is open before any is sent: a tile whose rays all
        # miss the scene completes with its first results, and must not
        # close the iteration.
        jobs = [self._new_job("eye", count, eye_iteration=e.index) for _, count in tiles]
        e.open_jobs = len(jobs)
        by_tracer: dict[str, list] = {}
        for j, (start, count), k in zip(jobs, tiles, self.tile_chunks):
            t = self._least_loaded(k)
            t.sent_since_report += count
            t.rays_sent += count
            self.jobs[j].sent, self.jobs[j].progress_s, self.jobs[j].sent_s = True, self._now, self._now
            by_tracer.setdefault(t.id, []).append((j, start, count))
        return [self._eye_job(tid, e.index, group)
                for tid, tiles in by_tracer.items() for group in _messages(tiles)]

    def _next_eye_index(self) -> int:
        """The next eye iteration's index: the next that installs its hit
        points (`keeps_hit_points`) while photons wait for a set (at the
        start, on resuming, or after the one that would have installed was
        discarded with a lost tracer), else the next. An index skipped is a
        random stream left unused, whatever it would have seen."""
        i, k = self.eye_started, self.hit_point_stride
        waiting = self.cull_box is None and not any(keeps_hit_points(e, k) for e in self.eyes)
        return -(-i // k) * k if waiting else i

    def _eye_job(self, tid: str, eye_iteration: int, tiles: list) -> Out:
        """The eye_job message of `tiles` [(job, pixel start, count)], with
        their whole credit: the tracer returns it, and reports the rays
        that miss the scene as escaped path ends."""
        ids, starts, counts = (np.array(c, np.int64) for c in zip(*tiles))
        return Out(tid, "eye_job", dict(eye_iteration=eye_iteration, job_ids=ids, pixel_starts=starts,
                                        counts=counts, credit_job=ids,
                                        credit_exp=np.zeros(len(ids), np.int64)))

    def _least_loaded(self, chunk: int) -> TracerInfo:
        """Of the tracers serving `chunk` (-1, a tile missing the scene: any
        tracer of the camera's chunks)."""
        owners = self.owners[chunk] if chunk >= 0 else \
            dict.fromkeys(i for k in self.camera_chunks for i in self.owners[k])
        return min((self.tracers[i] for i in owners), key=lambda t: t.load_estimate)

    def _finish_eye_iteration(self, e: EyeIteration) -> None:
        """Its hit points installed if it is one of those that keep them
        (`keeps_hit_points`: tracers send no others), else its emission only."""
        hits, _ = e.results.complete()
        kept = keeps_hit_points(e.index, self.hit_point_stride)
        # Its light is at the tracers (`hold_light`), collected in rounds (eye_light.py).
        self._eye_update(Update("hits", hits=hits if kept else None, eye_iteration=e.index))
        self.light.complete(e.index)
        self.eye_completed += 1


def _messages(tiles: list) -> list[list]:
    """A tracer's tiles in messages of at most EYE_RAYS_PER_MESSAGE rays (a
    tile larger than that alone)."""
    out, rays = [[]], 0
    for tile in tiles:
        if out[-1] and rays + tile[2] > EYE_RAYS_PER_MESSAGE:
            out, rays = out + [[]], 0
        out[-1].append(tile)
        rays += tile[2]
    return out
