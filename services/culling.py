"""Which deposits a photon job adds: those inside the cull box the job was
sent with (§4.3). Shared by the server's held deposits, the tracers'
epochs (services/tracer/epochs.py) and the ledger's re-trace, so all three
count the same deposits."""
from __future__ import annotations

import numpy as np

from dosppm_core.jobs import PhotonDeposits


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
