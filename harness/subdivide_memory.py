"""How much memory the subdivider needs, against the size of the scene
(issue 17). A harness, not part of rendering: each measurement runs the
subdivider in a fresh Python process, which loads its kernels first (a
tiny subdivision), then resets its peak (VmHWM, through
/proc/self/clear_refs) and subdivides the soup; the working memory is the
peak less the resident size before it.

    python -m harness.subdivide_memory --triangles 5e6 15e6 40e6 \\
        --budget 128MiB --work /tmp/sub-mem --json benchmarks/results/subdivide-memory.json
"""
from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys

from dosppm_core.chunks.subdivide import DEFAULT_GRID

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))

_CHILD = """
import json, os, sys
from dosppm_core.chunks.subdivide import subdivide
from dosppm_core.scene import builtin
from dosppm_core.scene.soup import SceneSource
from dosppm_core.scene.soupfile import open_soup
soup, out, budget, memory, grid = sys.argv[1], sys.argv[2], int(sys.argv[3]), int(sys.argv[4]), int(sys.argv[5])
def status(key):
    with open("/proc/self/status") as f:
        return next(int(l.split()[1]) * 1024 for l in f if l.startswith(key))
subdivide(SceneSource(builtin.make("cornell-box")), out + ".warm", chunks=2)   # kernels loaded
with open("/proc/self/clear_refs", "w") as f:
    f.write("5")
before = status("VmRSS")
report = subdivide(open_soup(soup), out, budget_bytes=budget, memory_bytes=memory, grid=grid)
print(json.dumps({"before_bytes": before, "peak_bytes": status("VmHWM"), "chunks": report.chunk_count,
                  "seconds": report.seconds}))
"""


def measure(soup: str, out: str, budget_bytes: int, memory_bytes: int, grid: int = DEFAULT_GRID) -> dict:
    """Subdivide `soup` into `out` in a fresh process; its memory figures:
    before_bytes, peak_bytes, working_bytes (= peak - before), and the
    soup's size."""
    env = dict(os.environ, PYTHONPATH=ROOT + os.pathsep + os.environ.get("PYTHONPATH", ""))
    for path in (out, out + ".warm"):
        shutil.rmtree(path, ignore_errors=True)
    run = subprocess.run([sys.executable, "-c", _CHILD, soup, out, str(budget_bytes), str(memory_bytes), str(grid)],
                         capture_output=True, text=True, env=env)
    if run.returncode != 0:
        raise RuntimeError(f"subdivide of {soup} failed: {run.stderr.strip()[-2000:]}")
    doc = json.loads(run.stdout.strip().splitlines()[-1])
    doc["working_bytes"] = doc["peak_bytes"] - doc["before_bytes"]
    doc["scene_bytes"] = sum(os.path.getsize(os.path.join(soup, n)) for n in os.listdir(soup))
    return doc


def main(argv=None) -> int:
    from dosppm_core.scene.generate import generate_building
    from services.config import parse_bytes
    from harness.provenance import write_results
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--triangles", type=float, nargs="+", default=[5e6, 15e6, 40e6])
    p.add_argument("--budget", default="128MiB", help="memory per chunk (the subdivider's --budget)")
    p.add_argument("--memory", default="256MiB", help="the subdivider's own working memory (--memory)")
    p.add_argument("--work", default="/tmp/dosppm-subdivide-memory")
    p.add_argument("--json", default=None)
    args = p.parse_args(argv)
    budget, memory = parse_bytes(args.budget, "--budget"), parse_bytes(args.memory, "--memory")
    rows = []
    for n in (int(t) for t in args.triangles):
        soup = os.path.join(args.work, f"building-{n}")
        if not os.path.exists(os.path.join(soup, "soup.msgpack")):
            generate_building(soup, triangles=n)
        row = dict(measure(soup, os.path.join(args.work, f"store-{n}"), budget, memory), triangles=n)
        rows.append(row)
        print(f"{n:,} triangles ({row['scene_bytes'] / 2**20:,.0f} MiB): peak RSS "
              f"{row['peak_bytes'] / 2**20:,.0f} MiB, working {row['working_bytes'] / 2**20:,.0f} MiB",
              flush=True)
        shutil.rmtree(os.path.join(args.work, f"store-{n}"), ignore_errors=True)
    if args.json:
        write_results(args.json, {"budget_bytes": budget, "memory_bytes": memory, "rows": rows})
    return 0


if __name__ == "__main__":
    sys.exit(main())
