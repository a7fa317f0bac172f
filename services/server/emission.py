"""`ServerState`'s emission: how many photon jobs are wanted in flight
(§3.3's 1k, or what the tracers' queues ask for, bounded by the deposits
held), and how they go out: as (id, rng key, count) to the tracers of the
lights' chunks, each message to the one with the most queue allowance
left. Also the alternating schedule DOSPPM improves on (Figure 15). A
mixin of services/server/state.py.

"Queue allowance" (rays a tracer may have queued before it gets no more
photon jobs) is flow control; "credit" is job completion only
(services/credit.py).
"""
from __future__ import annotations

import numpy as np

from services.server.costs import thread_cpu
from services.server.held import DISCARDED
from services.server.records import TracerInfo
from services.wire import MAX_EMITTED, Out

MESSAGE_RAYS = 32_768             # a tracer's queue allowance is never below this (rays)
TOTAL_ALLOWANCE_RAYS = 1 << 20    # rays queued at all tracers together, at most (see `queue_allowance`)
EMIT_PHOTONS_PER_TICK = 1 << 17   # so long queues (`allowance_of`) do not hold the loop from heartbeats
JOBS_PER_MESSAGE = 16     # photon jobs a tracer emits in one kernel call (one per job costs more)


class EmissionMixin:
    @property
    def queue_allowance(self) -> int:
        """Rays a tracer may have queued before it gets no more photon jobs:
        `queue_target_rays`, shared out when many tracers join, so the
        photon jobs in the server's outboxes and tracers' pipes stay under
        TOTAL_ALLOWANCE_RAYS whatever their number (16 tracers: 65,536 each)."""
        share = TOTAL_ALLOWANCE_RAYS // max(len(self.tracers), 1)
        return min(self.queue_target, max(MESSAGE_RAYS, share))

    def allowance_of(self, t: TracerInfo) -> int:
        """The server's queue allowance, or the longer queue the tracer asks for to hide its chunk loads."""
        return max(self.queue_allowance, t.queue_target)

    def _photon_jobs_wanted(self) -> int:
        """`min_photon_jobs` (the paper's 1k), or as many as the queues tracers
        ask for hold; but no more than the deposits held fit (`HeldDeposits`)."""
        ppj = self.settings.photons_per_job
        asked = sum(t.queue_target for t in self.tracers.values())
        # Out of core a job stays in flight until its last path ends, sweeps
        # after most of its rays have left the queues: such jobs take no
        # queue room, so they do not count against the queues asked for.
        # (Counted, they left the tracers' queues at a fifth of their target.)
        sent = self.photon_jobs_in_flight - len(self._photon_pending)
        queued = sum(t.load_estimate for t in self.tracers.values())
        spent = max(0, sent - -(-queued // ppj)) if asked else 0
        wanted = max(self.min_photon_jobs, -(-asked // ppj) + spent)
        c = self.counters
        per_photon = c["deposits_received"] / c["photon_paths_ended"] if c["photon_paths_ended"] else None
        return min(wanted, self.held.jobs_that_fit(ppj, per_photon))

    @thread_cpu("job_making_cpu_s")
    def _make_photon_jobs(self) -> None:
        wanted = self._photon_jobs_wanted()
        while self.photon_jobs_in_flight < wanted and self._epoch_room():
            self._photon_pending.append(self._new_job("photon", self.settings.photons_per_job))

    def _epoch_room(self) -> bool:
        """Gathering at the tracers, no job is made past OPEN_EPOCHS epochs
        from the next to apply: what tracers hold stays bounded."""
        return self.epochs is None or self.epochs.room_for(self.next_job)

    def _emitters(self) -> list[TracerInfo]:
        """The tracers serving a chunk a light lies in: photon paths start
        there, so most photons they make stay in their own queues."""
        ids = dict.fromkeys(i for k in self.light_chunks for i in self.owners[k])   # in a fixed order
        return [self.tracers[i] for i in ids if i in self.tracers]

    @thread_cpu("job_making_cpu_s")
    def _send_photon_jobs(self) -> list[Out]:
        """Photon jobs go out as (id, rng key, count), each message to the
        emitting tracer with the most queue allowance left, and no larger
        than what is left or its share of the pending jobs: emission
        spreads, and a slow tracer is never sent more than one job past its
        queue allowance. It queues the photons or passes them on
        (`TracerState.emit`); they count against its queue until it reports."""
        out, sent, ppj = [], 0, self.settings.photons_per_job
        emitters = self._emitters()
        while self._photon_pending and emitters and sent < EMIT_PHOTONS_PER_TICK and not self.held.full:
            t = max(emitters, key=lambda t: self.allowance_of(t) - t.load_estimate)
            left = self.allowance_of(t) - t.load_estimate
            if left <= 0:
                break
            # Its share of the pending: with 16 in flight one message took all.
            share = -(-len(self._photon_pending) // len(emitters))
            n = min(-(-left // ppj), JOBS_PER_MESSAGE, MAX_EMITTED // ppj, share)
            out.append(self._photon_job(t, [self._photon_pending.popleft() for _ in range(n)]))
            sent += int(out[-1].fields["counts"].sum())
        return out

    def _photon_job(self, t: TracerInfo, group: list[int]) -> Out:
        """The photon_job message of the jobs `group` for tracer `t`, with
        their whole credit; their photons count as emitted now."""
        jobs = [self.jobs[j] for j in group]
        ids = np.array(group, np.int64)
        counts = np.array([job.paths for job in jobs], np.int64)
        for job in jobs:       # the cull box for the ledger: the box it is sent with
            job.sent, job.progress_s, job.sent_s, job.cull_box = True, self._now, self._now, self.cull_box
        photons = int(counts.sum())
        t.sent_since_report += photons
        t.rays_sent += photons
        self.counters["photons_emitted"] += photons
        return Out(t.id, "photon_job", dict(
            job_ids=ids, rng_keys=np.array([job.rng_key for job in jobs], np.int64), counts=counts,
            cull_box=self.cull_box, credit_job=ids, credit_exp=np.zeros(len(ids), np.int64)))

    def _alternate(self) -> list[Out]:
        """The schedule DOSPPM improves on (Figure 15, 'alternating'): an
        eye pass, then `photons_per_iteration` photons, each waiting for
        the other to finish."""
        if self.eyes or self.photon_jobs_in_flight:
            return self._send_photon_jobs() if self._photon_pending else []
        if not self.eye_started or self.counters["photons_emitted"] - self._photons_at_eye_start \
                >= self.settings.photons_per_iteration:
            return self._maybe_start_eye_iteration()
        if self.cull_box is None or self.paused:
            return []
        left = self.settings.photons_per_iteration
        while left > 0:
            count = min(self.settings.photons_per_job, left)
            self._photon_pending.append(self._new_job("photon", count))
            left -= count
        return self._send_photon_jobs()

    def stop_emitting(self) -> None:
        """No new jobs; jobs created but not sent are dropped (never emitted,
        never counted)."""
        self.emitting = False
        for j in self._photon_pending:
            del self.jobs[j]
            self._job_status.set(j, DISCARDED)
            self.photon_jobs_in_flight -= 1
            if self.epochs is not None:
                self.epochs.dropped(j)
        self._photon_pending.clear()
