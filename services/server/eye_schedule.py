"""`ServerState`'s eye iterations: each is split into tiles (§5.6), its
rays routed by start chunk to the least loaded tracer serving it, with up
to `eye_in_flight` iterations traced at once; a complete one hands its hit
points over. A mixin of services/server/state.py.
"""
from __future__ import annotations

import numpy as np

from dosppm_core.chunks.view import start_eye_paths
from dosppm_core.jobs import HitPoints, RayBatch
from dosppm_core.trace import eye_ray_job
from services.credit import new_job
from services.server.job_messages import JobMessages
from services.server.records import EyeIteration, TracerInfo, Update
from services.wire import Out


class EyeScheduleMixin:
    def _maybe_start_eye_iteration(self) -> list[Out]:
        s = self.settings
        if len(self.eyes) >= self.eye_in_flight or (
                self.eye_started and not self._eye_restart and
                self.counters["photons_emitted"] - self._photons_at_eye_start < s.photons_per_iteration):
            return []
        self._eye_restart = False
        e = EyeIteration(self.eye_started, 0)
        self.eyes[e.index], self.eye_started = e, self.eye_started + 1
        self._photons_at_eye_start = self.counters["photons_emitted"]
        tiles = [(start, min(s.tile_pixels, self.n_pixels - start))
                 for start in range(0, self.n_pixels, s.tile_pixels)]
        # Every tile is open before any is routed: a tile whose rays all
        # miss the scene completes at once, and must not close the iteration.
        jobs = [self._new_job("eye", count, eye_iteration=e.index) for _, count in tiles]
        e.open_jobs = len(jobs)
        parts = JobMessages()
        for j, (start, count) in zip(jobs, tiles):
            batch = eye_ray_job(self.header, s.seed, e.index, start, count)
            batch.job[:] = j
            self._route(j, batch, parts)
        return [Out(tid, "eye_job", dict(eye_iteration=e.index, chunk=k, **parts.take((tid, k))))
                for tid, k in list(parts)]

    def _route(self, j: int, batch: RayBatch, parts: JobMessages) -> None:
        """Split a new eye job's paths by start chunk into `parts` per
        (tracer, chunk), each with its share of the job's credit; paths
        that miss the scene end here, seeing the environment."""
        routed, lost, seen = start_eye_paths(self.tree, batch, self._env)
        self.path_ends[1] += lost           # ESCAPED, before any tracer saw them
        self.eyes[self.jobs[j].eye_iteration].results.add(HitPoints.empty(), *seen)
        exp, kept = new_job(len(routed))
        share = (np.array([j], np.int64), np.array([exp], np.int64))
        for k, part in routed.items():
            t = self._least_loaded(k)
            t.sent_since_report += len(part)
            t.rays_sent += len(part)
            parts.add((t.id, k), part, share)
        self.jobs[j].sent, self.jobs[j].progress_s, self.jobs[j].sent_s = True, self._now, self._now
        self._credit(j, kept)               # the server's own share: all of it when none was sent

    def _least_loaded(self, chunk: int) -> TracerInfo:
        return min((self.tracers[i] for i in self.owners[chunk]), key=lambda t: t.load_estimate)

    def _finish_eye_iteration(self, e: EyeIteration) -> None:
        hits, emitted_light = e.results.complete()
        self._eye_update(Update("hits", hits=hits, emitted_light=emitted_light, eye_iteration=e.index))
        self.counters["hit_points"] += len(hits)
        self.eye_completed += 1
