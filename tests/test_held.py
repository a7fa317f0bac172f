"""The server's held deposits (services/server/held.py) against a plain
reference: over many batches, with jobs ending in random order, a split
commits exactly the deposits of the jobs complete since the last one that
lie in their own cull box, counts the discarded jobs' deposits, and keeps
the rest, whatever the parts' order and their jobs' interleaving."""
from __future__ import annotations

import numpy as np

from dosppm_core.jobs import PhotonDeposits
from services.server.held import COMPLETE, DISCARDED, IN_FLIGHT, HeldDeposits, HeldPart, split_held


_made = [0]


def _deposits(rng, jobs: np.ndarray, n: int) -> PhotonDeposits:
    pos = rng.uniform(-1, 1, (n, 3)).astype(np.float32)
    z = np.zeros((n, 3), np.float32)
    # Each row's serial number rides in flux[:, 0] (exact in float32 below
    # 2^24), so the test can name every row.
    flux = np.zeros((n, 3), np.float32)
    flux[:, 0] = _made[0] + np.arange(n)
    _made[0] += n
    return PhotonDeposits(pos, z, flux, job=rng.choice(jobs, n))


def _rows(parts) -> set:
    return {(int(j), float(f)) for p in parts for j, f in zip(p.job, p.flux[:, 0])}


def _held_rows(held: HeldDeposits) -> set:
    return _rows([p.deposits.take(np.repeat(p.open, p.ends - p.starts)) for p in held.parts])


def test_a_split_commits_exactly_the_deposits_of_jobs_complete_since_the_last():
    rng = np.random.default_rng(3)
    n_jobs = 60
    status = np.full(n_jobs, IN_FLIGHT, np.int8)
    boxes = np.tile(np.array([[-1.0] * 3, [1.0] * 3]), (n_jobs, 1, 1))
    boxes[::7, 1, 0] = 0.0           # some jobs were sent with a box that excludes x > 0
    held, reference = HeldDeposits(1 << 20, 1 << 30), []
    committed_ever = set()
    for round_ in range(12):
        for _ in range(rng.integers(1, 6)):
            live = np.flatnonzero(status == IN_FLIGHT)
            if len(live):
                d = _deposits(rng, live, int(rng.integers(1, 400)))
                held.add(d)
                reference.append(d)
        ending = rng.choice(np.flatnonzero(status == IN_FLIGHT), size=min(5, int(np.sum(status == IN_FLIGHT))),
                            replace=False)
        ended_now = {int(j): (DISCARDED if rng.random() < 0.2 else COMPLETE) for j in ending}
        for j, s in ended_now.items():
            status[j] = s
        ready = np.array(sorted(j for j, s in ended_now.items() if s == COMPLETE), np.int64)
        jobs = (ready, ready, ready, boxes[ready])
        commit, discarded = held.split(lambda ids: status[ids], jobs, float(round_))

        every = PhotonDeposits.concat(reference)
        inside = np.all((every.position >= boxes[every.job, 0]) & (every.position <= boxes[every.job, 1]), axis=1)
        ended_rows = np.isin(every.job, ready)
        expected = _rows([every.take(ended_rows & inside)])
        assert _rows(commit) == expected
        assert not (expected & committed_ever)           # each deposit once
        committed_ever |= expected
        gone = np.isin(every.job, [j for j, s in ended_now.items() if s == DISCARDED])
        assert discarded == int(gone.sum())
        still = np.isin(every.job, np.flatnonzero(status == IN_FLIGHT))
        assert _held_rows(held) == _rows([every.take(still)])
        assert held.rows == int(still.sum())
        reference = [every.take(still)]


def test_a_part_whose_jobs_are_all_in_flight_is_kept_as_it_is():
    """The split's cost is the rows of jobs that ended, not the hold: a
    part none of whose jobs ended is kept, not copied."""
    rng = np.random.default_rng(5)
    status = np.array([IN_FLIGHT, IN_FLIGHT, COMPLETE], np.int8)
    waiting, mixed = HeldPart(_deposits(rng, np.array([0, 1]), 50)), HeldPart(_deposits(rng, np.array([1, 2]), 50))
    rows_before, of_job_2 = mixed.rows, int(np.sum(mixed.deposits.job == 2))
    ready = np.array([2], np.int64)
    boxes = np.array([[[-1.0] * 3, [1.0] * 3]])
    commit, keep, discarded = split_held([waiting, mixed], lambda ids: status[ids], (ready, ready, ready, boxes))
    assert keep[0] is waiting and keep[0].deposits is waiting.deposits
    assert sum(len(c) for c in commit) == of_job_2 > 0
    assert keep[1].rows == rows_before - of_job_2
    assert discarded == 0
