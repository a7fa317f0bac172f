"""The deposits the server holds until their photon job is complete
(exactly-once accounting): which of them a batch commits, which wait, and
when a batch is due. Pure: the held parts, the jobs' status, the clock."""
from __future__ import annotations

import numpy as np

from dosppm_core.chunks.pacing import DEPOSIT_BYTES
from dosppm_core.jobs import PhotonDeposits

UNKNOWN, IN_FLIGHT, COMPLETE, DISCARDED = 0, 1, 2, 3     # photon job status
DEPOSITS_PER_PHOTON_GUESS = 4.0   # before any photon path has ended
FULL_BATCH_INTERVAL_S = 1.0     # while full, a batch at most this often (each one reads all held)


class HeldDeposits:
    """The held deposits and when to hand a batch over: once `photon_batch`
    more are held than after the last (server batching, §4.3), or, once
    they fill `limit_bytes`, as soon as some job has completed. While full
    the server sends no photon job (`full`), so what it holds is bounded
    by the limit, not by the photons the tracers' queues ask for (issue 17:
    562 MiB against a 400 MiB limit at 119 chunks)."""

    def __init__(self, photon_batch: int, limit_bytes: float):
        self.parts: list[PhotonDeposits] = []
        self.rows, self.photon_batch = 0, int(photon_batch)
        self.limit_rows = max(1, int(limit_bytes // DEPOSIT_BYTES))
        self._next_at, self._last_split_s = self.photon_batch, float("-inf")

    def jobs_that_fit(self, photons_per_job: int, deposits_per_photon: float | None) -> int:
        """Photon jobs in flight whose deposits fit the limit less a batch of
        complete jobs' not yet handed over (half the limit at most). A job's
        deposits are held until its last path ends, and out of core that is
        many sweeps later: what is held is every deposit of every job in flight.
        `deposits_per_photon`: deposits received per photon path ended (high
        while paths are young, so it errs safe); GUESS before any end."""
        per_job = photons_per_job * (deposits_per_photon or DEPOSITS_PER_PHOTON_GUESS)
        room = max(self.limit_rows / 2, self.limit_rows - self.photon_batch)
        return max(1, int(room / max(per_job, 1.0)))

    @property
    def full(self) -> bool:
        return self.rows >= self.limit_rows

    def add(self, deposits: PhotonDeposits) -> None:
        self.parts.append(deposits)
        self.rows += len(deposits)

    def due(self, now: float, jobs_ready: bool) -> bool:
        return self.rows >= self._next_at or (
            self.full and jobs_ready and now - self._last_split_s >= FULL_BATCH_INTERVAL_S)

    def split(self, status_of, jobs: tuple, now: float) -> tuple[list, int]:
        """(deposits to commit, discarded jobs' deposit count); the rest is
        kept (`split_held`)."""
        held, self.parts = self.parts, []
        commit, self.parts, discarded = split_held(held, status_of, jobs)
        self.rows = sum(len(k) for k in self.parts)
        self._next_at, self._last_split_s = self.rows + self.photon_batch, now
        return commit, discarded


def split_held(held: list, status_of, jobs: tuple) -> tuple[list, list, int]:
    """(deposits to commit: of complete jobs, inside their own cull boxes;
    to keep: of jobs in flight; the count of discarded jobs' deposits),
    part by part, each part dropped from `held` once split: the server's
    peak is what it holds plus one part, not that and copies of all of it.
    `status_of(job ids)` gives each deposit's job status; `jobs` are the
    complete jobs' columns (ids, rng keys, paths, cull boxes)."""
    held.reverse()
    commit, keep, discarded = [], [], 0
    while held:
        part = held.pop()
        status = status_of(part.job)
        discarded += int(np.sum(status == DISCARDED))
        live, done = status == IN_FLIGHT, status == COMPLETE
        if done.any():
            done &= _own_box_mask(part, jobs)
        for out, mask in ((keep, live), (commit, done)):
            if mask.all():
                out.append(part)
            elif mask.any():
                out.append(part.take(mask))
        del part
    return commit, keep, discarded


def _own_box_mask(deposits: PhotonDeposits, jobs: tuple) -> np.ndarray:
    """Which deposits lie inside the cull box their own job was sent with.
    A tracer culls a coalesced package against the union of its jobs'
    boxes, which keeps more; culling again here makes what a job adds a
    function of the job alone, so the ledger can re-trace it
    (services/ledger.py). Deposits of jobs not in `jobs` pass."""
    ids, _keys, _paths, boxes = jobs
    if len(deposits) == 0 or len(ids) == 0 or np.isinf(boxes).all():
        return np.ones(len(deposits), bool)
    at = np.minimum(np.searchsorted(ids, deposits.job), len(ids) - 1)
    box = boxes[at]
    p = deposits.position
    return np.all((p >= box[:, 0]) & (p <= box[:, 1]), axis=1) | (ids[at] != deposits.job)


def within_own_boxes(deposits: PhotonDeposits, jobs: tuple) -> PhotonDeposits:
    """The deposits inside their own job's cull box (`_own_box_mask`)."""
    inside = _own_box_mask(deposits, jobs)
    return deposits if inside.all() else deposits.take(inside)
