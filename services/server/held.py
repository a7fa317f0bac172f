"""The deposits the server holds until their photon job is complete
(exactly-once accounting): which of them a batch commits, which wait, and
when a batch is due. Pure: the held parts, the jobs' status, the clock."""
from __future__ import annotations

import numpy as np

from dosppm_core.chunks.pacing import DEPOSIT_BYTES
from dosppm_core.jobs import PhotonDeposits
from services.culling import within_own_boxes
from services.server.costs import thread_cpu

UNKNOWN, IN_FLIGHT, COMPLETE, DISCARDED = 0, 1, 2, 3     # photon job status
DEPOSITS_PER_PHOTON_GUESS = 4.0   # before any photon path has ended
FULL_BATCH_INTERVAL_S = 1.0     # while full, a batch at most this often


class JobStatus:
    """Each photon job's status by id, from `first` on (UNKNOWN for ids
    never made, and for those of the server this one resumed from)."""

    def __init__(self, first: int):
        self.first, self.codes = int(first), np.zeros(1024, np.int8)

    def __call__(self, ids: np.ndarray) -> np.ndarray:
        i = ids - self.first
        ok = (i >= 0) & (i < len(self.codes))
        return np.where(ok, self.codes[np.where(ok, i, 0)], UNKNOWN)

    def set(self, j: int, status: int) -> None:
        i = j - self.first
        if i >= len(self.codes):
            self.codes = np.concatenate([self.codes, np.zeros(max(i + 1, len(self.codes)), np.int8)])
        self.codes[i] = status


class HeldDeposits:
    """The held deposits and when to hand a batch over: once `photon_batch`
    more are held than after the last (server batching, §4.3), or, once
    they fill `limit_bytes`, as soon as some job has completed. While full
    the server sends no photon job (`full`), so what it holds is bounded
    by the limit, not by the photons the tracers' queues ask for (issue 17:
    562 MiB against a 400 MiB limit at 119 chunks)."""

    def __init__(self, photon_batch: int, limit_bytes: float):
        self.parts: list[HeldPart] = []
        self.rows, self.photon_batch = 0, int(photon_batch)
        self.limit_rows = max(1, int(limit_bytes // DEPOSIT_BYTES))
        self._next_at, self._last_split_s = self.photon_batch, float("-inf")
        self.cpu_s = 0.0     # CPU in add and split: a part of the server's cost per photon (costs.py)

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

    @thread_cpu("cpu_s")
    def add(self, deposits: PhotonDeposits) -> None:
        self.parts.append(HeldPart(deposits))
        self.rows += len(deposits)

    def due(self, now: float, jobs_ready: bool) -> bool:
        return self.rows >= self._next_at or (
            self.full and jobs_ready and now - self._last_split_s >= FULL_BATCH_INTERVAL_S)

    @thread_cpu("cpu_s")
    def split(self, status_of, jobs: tuple, now: float) -> tuple[list, int]:
        """(deposits to commit, discarded jobs' deposit count); the rest is
        kept (`split_held`)."""
        held, self.parts = self.parts, []
        commit, self.parts, discarded = split_held(held, status_of, jobs)
        self.rows = sum(len(k) for k in self.parts)
        self._next_at, self._last_split_s = self.rows + self.photon_batch, now
        return commit, discarded


class HeldPart:
    """The deposits of one results message, grouped by job, of which the
    rows of jobs still in flight are held. A split reads a part's rows only
    for the jobs that ended since the last, and compacts it once half its
    rows are gone. Out of core a job's last path ends many sweeps after its
    first (the slowest of its photons), so nearly every part holds some job
    still in flight and what is held is many batches deep: reading all of
    it at every batch made each batch cost the whole hold (about 2 s at
    14M held deposits on the 5M building, growing with the hold, until
    tracers took the silent server for gone)."""

    def __init__(self, deposits: PhotonDeposits):
        job = deposits.job
        if len(job) > 1 and (job[1:] < job[:-1]).any():
            deposits = deposits.take(np.argsort(job, kind="stable"))
        self.deposits = deposits
        self.jobs, self.starts = np.unique(deposits.job, return_index=True)
        self.ends = np.append(self.starts[1:], len(deposits))
        self.open = np.ones(len(self.jobs), bool)       # jobs whose rows are held
        self.rows = len(deposits)

    def __len__(self) -> int:
        return self.rows

    def settle(self, status_of, jobs: tuple) -> tuple[PhotonDeposits | None, int]:
        """Let go of the rows of jobs that ended: (those of complete jobs
        inside their own cull boxes, the count of discarded jobs' rows)."""
        status = status_of(self.jobs)
        ended = self.open & (status != IN_FLIGHT)
        if not ended.any():
            return None, 0
        lengths = self.ends - self.starts
        done = ended & (status == COMPLETE)
        commit = None
        if done.any():
            commit = within_own_boxes(self.deposits.take(_ranges(self.starts[done], self.ends[done])), jobs)
        discarded = int(lengths[ended & (status == DISCARDED)].sum())
        self.open &= ~ended
        self.rows -= int(lengths[ended].sum())
        if 0 < self.rows <= len(self.deposits) // 2:
            self._compact()
        return commit, discarded

    def _compact(self) -> None:
        keep = self.open
        self.deposits = self.deposits.take(_ranges(self.starts[keep], self.ends[keep]))
        lengths = (self.ends - self.starts)[keep]
        self.jobs, self.ends = self.jobs[keep], np.cumsum(lengths)
        self.starts = self.ends - lengths
        self.open = np.ones(len(self.jobs), bool)


def _ranges(starts: np.ndarray, ends: np.ndarray) -> np.ndarray:
    """The indices [s, e) of every range, one after the other."""
    lengths = ends - starts
    offsets = np.repeat(starts - (np.cumsum(lengths) - lengths), lengths)
    return np.arange(int(lengths.sum())) + offsets


def split_held(held: list, status_of, jobs: tuple) -> tuple[list, list, int]:
    """(deposits to commit: of complete jobs, inside their own cull boxes;
    parts still holding rows of jobs in flight; the count of discarded
    jobs' deposits). `status_of(job ids)` gives each job's status; `jobs`
    are the complete jobs' columns (ids, rng keys, paths, cull boxes).
    Parts are dropped from `held` as they are settled: the server's peak
    is what it holds plus what the batch commits, not twice the hold (the
    last batch commits all of it)."""
    held.reverse()
    commit, keep, discarded = [], [], 0
    while held:
        part = held.pop()
        rows, lost = part.settle(status_of, jobs)
        discarded += lost
        if rows is not None and len(rows):
            commit.append(rows)
        if part.rows:
            keep.append(part)
    return commit, keep, discarded
