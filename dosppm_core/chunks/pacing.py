"""How much work to gather before sweeping the chunks, so that tracing
hides the chunk loads (issue 17).

When not every chunk fits in memory, each sweep over the chunks loads
them again: the loads cost a fixed time per sweep, the tracing grows with
the work the sweep carries. OSPPM's photons per iteration and a DOSPPM
tracer's queue of rays are that work. Both grow until the loads are at
most `LOAD_SHARE` of a sweep, within a memory limit for the queued rays
(`--queue-memory`): the paper's "load the next chunk when all its jobs
are processed" pays off only when there are enough jobs.
"""
from __future__ import annotations

import numpy as np

from dosppm_core.jobs import PhotonDeposits, RayBatch

GROWTH = 4                       # at most this factor per sweep
LOAD_SHARE = 0.1                 # chunk loads at most this share of a sweep's time
QUEUE_MEMORY_BYTES = 256 << 20   # default limit on queued rays (--queue-memory)
# A tracer's queued rays before any pacing: the server's default credit per
# tracer, and where a tracer's queue target starts growing.
FIRST_QUEUE_RAYS = 262_144


def _row_bytes(record) -> int:
    """Bytes per row of a job record (its SCHEMA's columns)."""
    return sum(np.dtype(dt).itemsize * int(np.prod(shape, dtype=np.int64)) for dt, shape in record.SCHEMA.values())


RAY_BYTES = _row_bytes(RayBatch)
DEPOSIT_BYTES = _row_bytes(PhotonDeposits)


def work_to_hide_loads(load_s: float, trace_s: float, work: float, share: float = LOAD_SHARE) -> float:
    """The work per sweep for which the loads are `share` of the sweep's
    time, from a sweep that loaded for `load_s` and traced `work` (rays,
    photons) in `trace_s`. Loads per sweep do not grow with the work, the
    tracing does. 0 when nothing was measured."""
    if load_s <= 0 or trace_s <= 0 or work <= 0:
        return 0.0
    return work / trace_s * load_s * (1.0 - share) / share


def grown(current: int, wanted: float, cap: int, first: bool = False) -> int:
    """`current` grown towards `wanted`, at most GROWTH times per step (one
    noisy sweep must not jump it; the first measurement may, since the
    ramp's small sweeps are the slow ones) and never past `cap`; never
    shrunk."""
    step = wanted if first else min(GROWTH * current, wanted)
    return int(min(cap, max(current, step)))


def queue_cap_rays(queue_memory_bytes: float | None) -> int:
    """Rays that fit in the queue memory limit."""
    limit = QUEUE_MEMORY_BYTES if queue_memory_bytes is None else queue_memory_bytes
    return max(1, int(limit // RAY_BYTES))


def deposit_batch_cap(queue_memory_bytes: float | None) -> int:
    """Deposits per statistics update that a quarter of the queue memory
    limit holds (OSPPM: the update's temporaries take about as much again).
    At the default limit that is above the paper's 1M, so only a smaller
    limit set by the user makes batches smaller."""
    limit = QUEUE_MEMORY_BYTES if queue_memory_bytes is None else queue_memory_bytes
    return max(1, int(limit // 4 // DEPOSIT_BYTES))
