"""The deposits the server holds until their photon job is complete
(exactly-once accounting): which of them a batch commits, and which wait.
Pure functions of the held parts and the jobs' status."""
from __future__ import annotations

import numpy as np

from dosppm_core.jobs import PhotonDeposits

UNKNOWN, IN_FLIGHT, COMPLETE, DISCARDED = 0, 1, 2, 3     # photon job status


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
