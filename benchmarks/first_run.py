"""Issue 29: the first render after `pip install .` against the warm one.

Each repeat installs the checkout (not editable) into a fresh virtual
environment with an empty numba cache, then renders the default scene for
--seconds twice: the first (it compiles the kernels before its clock) and
a warm second. Repeats alternate the working directory between the
checkout's root (where the README puts a new user; `python -m` there once
made tracers import the source tree and compile inside the clock) and a
directory elsewhere. The figure is the ratio of photons applied, first over
second, per run and as the median per working directory.

    python benchmarks/first_run.py [--seconds 20] [--repeats 4]

Writes benchmarks/results/first-run.json (about 3 min a repeat).
"""
from __future__ import annotations

import argparse
import glob
import json
import os
import statistics
import subprocess
import sys
import tempfile

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, ROOT)

from harness.provenance import write_results  # noqa: E402


def _render(dosppm: str, out: str, env: dict, cwd: str, seconds: float) -> int:
    subprocess.run([dosppm, "render", "--time", str(seconds), "--out", out, "--http", "off", "--quiet"],
                   cwd=cwd, env=env, check=True, timeout=seconds * 10 + 900)
    with open(os.path.splitext(out)[0] + ".json", encoding="utf-8") as f:
        return json.load(f)["counters"]["photons_committed"]


def one(work: str, where: str, seconds: float) -> dict:
    env = {k: v for k, v in os.environ.items() if not k.startswith(("PYTHONPATH", "NUMBA_CACHE_DIR"))}
    venv = os.path.join(work, "venv")
    subprocess.run([sys.executable, "-m", "venv", venv], check=True)
    subprocess.run([os.path.join(venv, "bin", "python"), "-m", "pip", "install", "-q", ROOT],
                   env=env, check=True)
    cwd = ROOT if where == "checkout" else work
    dosppm = os.path.join(venv, "bin", "dosppm")
    first = _render(dosppm, os.path.join(work, "first.exr"), env, cwd, seconds)
    second = _render(dosppm, os.path.join(work, "second.exr"), env, cwd, seconds)
    assert glob.glob(os.path.join(venv, "lib", "python3*", "site-packages", "dosppm_core"))
    return {"where": where, "first": first, "second": second, "ratio": first / second}


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--seconds", type=float, default=20.0)
    p.add_argument("--repeats", type=int, default=4)
    p.add_argument("--json", default=os.path.join(ROOT, "benchmarks", "results", "first-run.json"))
    args = p.parse_args(argv)
    runs = []
    for i in range(args.repeats):
        where = ("checkout", "elsewhere")[i % 2]
        with tempfile.TemporaryDirectory(prefix="dosppm-first-") as work:
            runs.append(one(work, where, args.seconds))
        r = runs[-1]
        print(f"{where:9s} first {r['first']:,} second {r['second']:,} ratio {r['ratio']:.2f}", flush=True)
    res = {"seconds": args.seconds, "runs": runs,
           "median_ratio": {w: statistics.median(r["ratio"] for r in runs if r["where"] == w)
                            for w in ("checkout", "elsewhere") if any(r["where"] == w for r in runs)}}
    print(res["median_ratio"])
    write_results(args.json, res)
    return 0


if __name__ == "__main__":
    sys.exit(main())
