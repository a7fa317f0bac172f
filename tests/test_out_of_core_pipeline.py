"""Out of core end to end, CI-sized (issue 17, part 2): a building whose
chunks, loaded, need at least twice the memory allowed to any one process
is generated, subdivided and rendered in OSPPM and DOSPPM (a server and two
`dosppm worker`s), each step its own process; every process's peak RSS
stays under the limit, and both images are finite and agree.

It runs `benchmarks/out_of_core_pipeline.py` as a child, not in this
process: a child's ru_maxrss starts from its parent's RSS at the fork, and
the test process is large by now (see tests/test_memory.py). The full-size
run (34M triangles, a store on disk twice the limit) is that script's
results file, benchmarks/results/out-of-core-pipeline.json.
"""
from __future__ import annotations

import json
import math

import pytest

from tests.helpers.cli import run_python
from tests.helpers.paths import REPO

pytestmark = pytest.mark.slow

# 7.5M triangles load as 1017 MiB of chunks: 2.03x this limit. Measured
# here: generate 142, subdivide 276, OSPPM 284, server 271, tracers 248 and
# 249 MiB; CI's machine has measured about 60 MiB more a process.
LIMIT_MIB = 500
# Run to run, the images' mean luminance is this close (issue 34). Measured
# on this test's store and flags (`dosppm render STORE --mode osppm
# --photons 150000 --memory 96MiB --queue-memory 16MiB --seed S`, and the
# server with 2 workers likewise): OSPPM at 4 seeds 0.37444, standard
# deviation 0.18%, range 0.40%; DOSPPM at 2 seeds +0.42% and +0.37% over
# that mean (its drain applies more photons: 352k and 950k against 184k),
# +0.39% at the same seed. The bound is that offset plus five standard
# deviations of a difference of two runs (5 x 1.41 x 0.18%), rounded up.
# The failure it was written for, a DOSPPM image holding no photon job,
# was 25% dark.
MEAN_TOLERANCE = 0.02


def test_a_scene_twice_the_memory_of_each_process_renders_within_the_limits(tmp_path):
    out = tmp_path / "pipeline.json"
    r = run_python(f"{REPO}/benchmarks/out_of_core_pipeline.py", "--triangles", "7.5e6",
                   "--limit", f"{LIMIT_MIB}MiB", "--memory", "96MiB", "--queue-memory", "16MiB",
                   "--photons", "150000", "--work", tmp_path / "work", "--json", out, timeout=900)
    assert r.returncode == 0, r.stderr[-3000:]
    doc = json.loads(out.read_text())
    print(r.stdout)
    # The scene is larger than any process may hold: loading every chunk
    # at once would break the limit twice over.
    assert doc["chunk_memory_over_limit"] >= 2.0
    assert doc["chunks"] >= 8
    assert set(doc["processes"]) == {"generate", "subdivide", "osppm", "server", "tracer 0", "tracer 1"}
    # Each process's own peak: the parent, which they are forked from, is
    # far smaller (measured last, when it is largest).
    assert doc["parent_rss_bytes"] < 0.5 * LIMIT_MIB * 2 ** 20
    peaks = {k: v["peak_bytes"] >> 20 for k, v in doc["processes"].items()}
    assert doc["over_limit"] == [], peaks
    lum = doc["mean_luminance"]
    assert all(math.isfinite(v) and v > 0 for v in lum.values()), lum
    # Two renders of the same scene by different modes, each stopped at the
    # same photon count and drained (not a deadline: out of core, a photon
    # job outlives a few seconds' render, and the deadline discards it
    # whole): the same mean within their noise.
    applied = {m: r["photons_applied"] for m, r in doc["renders"].items()}
    assert all(n >= 150_000 for n in applied.values()), applied
    assert abs(lum["osppm"] - lum["dosppm"]) < MEAN_TOLERANCE * lum["osppm"], (lum, applied)
