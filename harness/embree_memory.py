"""Measure what an Embree BVH costs in memory, the constant behind the
subdivider's chunk budget (`chunks.subdivide.EMBREE_BYTES_PER_TRIANGLE`).
A harness, not part of rendering: it starts a fresh Python process."""
from __future__ import annotations

import os
import subprocess
import sys

import numpy as np

from dosppm_core.accel import Accelerator
from dosppm_core.chunks.subdivide import EMBREE_BYTES_PER_VERTEX


def measure_embree_bytes_per_triangle(triangles: int = 1_000_000) -> float:
    """Re-measure EMBREE_BYTES_PER_TRIANGLE: peak RSS growth of an
    `Accelerator` over random overlapping triangles (the worst case), less
    EMBREE_BYTES_PER_VERTEX per vertex, per triangle. Runs in a fresh
    process: memory freed by an earlier build is reused and would hide the
    cost."""
    code = (f"from harness.embree_memory import _embree_peak_bytes; "
            f"print(_embree_peak_bytes({int(triangles)}))")
    root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    env = dict(os.environ, PYTHONPATH=root + os.pathsep + os.environ.get("PYTHONPATH", ""))
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         env=env, check=True).stdout
    peak, nt, nv = (int(x) for x in out.split())
    return (peak - EMBREE_BYTES_PER_VERTEX * nv) / nt


def _embree_peak_bytes(triangles: int) -> str:
    """'peak_bytes triangles vertices' of one BVH build in this process."""
    def status(key):
        with open("/proc/self/status") as f:
            return next(int(l.split()[1]) * 1024 for l in f if l.startswith(key))
    rng = np.random.default_rng(0)
    c = rng.random((triangles, 1, 3)) * 100 + rng.normal(0, 0.3, (triangles, 3, 3))
    v = c.reshape(-1, 3).astype(np.float32)
    t = np.arange(3 * triangles, dtype=np.int32).reshape(-1, 3)
    del c
    Accelerator(v[:3], t[:1]).close()          # load Embree and TBB first
    try:
        with open("/proc/self/clear_refs", "w") as f:
            f.write("5")                        # reset VmHWM to the current RSS
        key = "VmHWM"
    except OSError:
        key = "VmRSS"                           # no reset: final size only
    before = status("VmRSS")
    accel = Accelerator(v, t)
    peak = status(key) - before
    accel.close()
    return f"{peak} {triangles} {len(v)}"
