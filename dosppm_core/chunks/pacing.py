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

import os

import numpy as np

from dosppm_core.jobs import HitPoints, PhotonDeposits, RayBatch

GROWTH = 4                       # at most this factor per sweep
LOAD_SHARE = 0.1                 # chunk loads at most this share of a sweep's time
DWELL_MIN_S, DWELL_MAX_S = 0.25, 5.0    # `dwell_s`'s bounds
# A tracer's queue holds no more than it traces in this time (issue 31):
# a photon job waits for the queue ahead of it at each chunk it reaches.
LATENCY_S = 3.0
# The default limit on queued rays (--queue-memory) is this share of the
# memory the process may use, within these bounds: on a 24 GiB machine the
# upper bound, which lets OSPPM's photons per iteration grow until tracing
# hides the loads (8M photons on the 5M building; 256 MiB stopped it at 2M,
# 84% of the best hand-tuned setting), and inside a 400 MiB container the
# lower one.
QUEUE_MEMORY_SHARE = 1 / 16
QUEUE_MEMORY_MIN, QUEUE_MEMORY_MAX = 32 << 20, 1 << 30
# What a dosppm process holds before any chunk: the interpreter, numpy,
# numba's kernels and Embree (measured 170-185 MiB in issue 17's runs).
PROCESS_BASE_BYTES = 192 << 20
# A tracer's queued rays before any pacing: the server's default queue
# allowance per tracer, and where a tracer's queue target starts growing.
FIRST_QUEUE_RAYS = 262_144


def _row_bytes(record) -> int:
    """Bytes per row of a job record: its SCHEMA's columns, less the
    optional ones (a hit point's frame: 20 B more, in the few scenes with
    an anisotropic material)."""
    return sum(np.dtype(dt).itemsize * int(np.prod(shape, dtype=np.int64))
               for name, (dt, shape) in record.SCHEMA.items() if name not in record.OPTIONAL)


RAY_BYTES = _row_bytes(RayBatch)
DEPOSIT_BYTES = _row_bytes(PhotonDeposits)
HIT_POINT_BYTES = _row_bytes(HitPoints)
# Eye iterations traced at once, at most (issue 31). Out of core one chunk
# load then serves the eye rays of several; more would only delay the
# newest hit points further behind the photons.
EYE_IN_FLIGHT = 16


def work_to_hide_loads(load_s: float, trace_s: float, work: float, share: float = LOAD_SHARE) -> float:
    """The work per sweep for which the loads are `share` of the sweep's
    time, from a sweep that loaded for `load_s` and traced `work` (rays,
    photons) in `trace_s`. Loads per sweep do not grow with the work, the
    tracing does. 0 when nothing was measured."""
    if load_s <= 0 or trace_s <= 0 or work <= 0:
        return 0.0
    return work / trace_s * load_s * (1.0 - share) / share


def dwell_s(load_s: float, share: float = LOAD_SHARE) -> float:
    """Seconds to trace photons on a chunk before moving on (the chunk
    scheduler's dwell), for chunk loads of `load_s` each to be `share` of
    the time, within [DWELL_MIN_S, DWELL_MAX_S]."""
    return min(DWELL_MAX_S, max(DWELL_MIN_S, load_s * (1.0 - share) / share))


def grown(current: int, wanted: float, cap: int, first: bool = False) -> int:
    """`current` grown towards `wanted`, at most GROWTH times per step (one
    noisy sweep must not jump it; the first measurement may, since the
    ramp's small sweeps are the slow ones) and never past `cap`; never
    shrunk."""
    step = wanted if first else min(GROWTH * current, wanted)
    return int(min(cap, max(current, step)))


def cgroup_memory_limit(proc_self: str = "/proc/self", root: str = "/sys/fs/cgroup") -> int | None:
    """The tightest memory limit of this process's cgroup (v2) and its
    ancestors, or cgroup v1's; None when there is none. A container or a
    systemd slice sets it, and the machine's total then says nothing."""
    limits = []
    try:
        with open(os.path.join(proc_self, "cgroup"), encoding="utf-8") as f:
            lines = f.read().splitlines()
    except OSError:
        return None
    for line in lines:
        hierarchy, controllers, path = (line.split(":", 2) + ["", ""])[:3]
        if hierarchy == "0":            # v2: every ancestor's memory.max applies
            parts = [q for q in path.split("/") if q]
            for depth in range(len(parts) + 1):
                limits.append(_read_limit(os.path.join(root, *parts[:depth], "memory.max")))
        elif "memory" in controllers.split(","):
            limits.append(_read_limit(os.path.join(root, "memory", path.lstrip("/"), "memory.limit_in_bytes")))
    found = [x for x in limits if x is not None]
    return min(found) if found else None


def _read_limit(path: str) -> int | None:
    try:
        with open(path, encoding="utf-8") as f:
            text = f.read().strip()
    except OSError:
        return None
    # "max" (v2) or a page-rounded 2^63 (v1) mean no limit.
    return int(text) if text.isdigit() and int(text) < 1 << 62 else None


def machine_memory_bytes() -> int:
    """Memory this process may use: the machine's, or its cgroup's limit
    if that is lower."""
    total = os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")
    limit = cgroup_memory_limit()
    return min(total, limit) if limit else total


def default_queue_memory(machine_bytes: int | None = None) -> int:
    """--queue-memory when not given: QUEUE_MEMORY_SHARE of the process's
    memory, within [QUEUE_MEMORY_MIN, QUEUE_MEMORY_MAX]."""
    machine = machine_memory_bytes() if machine_bytes is None else machine_bytes
    return int(min(QUEUE_MEMORY_MAX, max(QUEUE_MEMORY_MIN, machine * QUEUE_MEMORY_SHARE)))


def default_chunk_memory(processes: int = 1, machine_bytes: int | None = None, at_least: int = 0) -> int:
    """--memory (resident chunks) when not given, for one of `processes`
    dosppm processes sharing this machine (a local render's server and
    tracers): its share of the memory a process may use, less what a
    process holds before any chunk (PROCESS_BASE_BYTES) and 1.5x its
    queue limit's default (the queue and the batch in hand); never less
    than `at_least` (a tracer's largest chunk, so that it can render).
    Before, a tracer held all its chunks, so on a scene larger than the
    machine two tracers asked for more than there is."""
    machine = machine_memory_bytes() if machine_bytes is None else machine_bytes
    share = machine / max(1, processes)
    return max(int(at_least), int(share - PROCESS_BASE_BYTES - 1.5 * default_queue_memory(machine)))


def queue_cap_rays(queue_memory_bytes: float | None) -> int:
    """Rays that fit in the queue memory limit."""
    limit = default_queue_memory() if queue_memory_bytes is None else queue_memory_bytes
    return max(1, int(limit // RAY_BYTES))


def deposit_batch_cap(queue_memory_bytes: float | None) -> int:
    """Deposits per statistics update that a quarter of the queue memory
    limit holds (OSPPM: the update's temporaries take about as much again).
    At the default limit that is above the paper's 1M, so only a smaller
    limit set by the user makes batches smaller."""
    limit = default_queue_memory() if queue_memory_bytes is None else queue_memory_bytes
    return max(1, int(limit // 4 // DEPOSIT_BYTES))


def eye_iterations_in_flight(pixels: int, queue_memory_bytes: float) -> int:
    """Eye iterations a server may trace at once: EYE_IN_FLIGHT, fewer when
    their hit points (one a pixel each, held until the iteration is
    complete) would take more than a quarter of the queue memory; one at
    least."""
    fit = int(queue_memory_bytes // 4 // max(1, pixels * HIT_POINT_BYTES))
    return max(1, min(EYE_IN_FLIGHT, fit))
