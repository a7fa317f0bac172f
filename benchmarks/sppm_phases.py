"""Issue 33's speed check: one-process SPPM on the built-in scene, this
tree against another checkout, phase by phase.

Each run is a fresh process of one tree (`PYTHONPATH=TREE python -P`,
so the other tree's library and kernels), rendering `--photons` photons
with the default settings, with wall-clock timers around the library's
calls: the eye pass (`trace_eye`) and within it the eye bounce
(`advance_eye`, the bounce kernels and the direct light's
`sample_direct`), the photon pass (`trace_photon_jobs`, within it
`scatter_photons`) and the statistics (`flush`). Trees alternate run by
run (this, other, other, this, ...) and the report gives each phase's
median over the runs and the median of the per-pair ratios.

Whole-process timing (`farm-bench` on `dosppm render --mode sppm`) says
whether a change costs; this says where. It found what the recorded-input
kernel benchmark (kernels.py) did not: the direct light's per-ray call of
`light_le` with the whole light tuple (about a quarter of `sample_direct`'s
time) and
the materials' flags recomputed at every bounce call.

    python benchmarks/sppm_phases.py --against /tmp/wt-old [--photons 5e6] [--pairs 3]

Writes benchmarks/results/sppm-phases.json.
"""
from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import time

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))

# (module, attribute) of the calls timed; a tree without one skips it.
TIMED = (("dosppm_core.modes.sppm", "trace_eye"), ("dosppm_core.modes.sppm", "trace_photon_jobs"),
         ("dosppm_core.modes.sppm", "emit_photon_job"), ("dosppm_core.trace", "advance_eye"),
         ("dosppm_core.trace", "scatter_photons"), ("dosppm_core.trace", "shadow_rays"),
         ("dosppm_core.kernels.paths", "advance_eye_paths"),
         ("dosppm_core.kernels.paths", "advance_eye_paths_serial"),
         ("dosppm_core.kernels.direct", "sample_direct"), ("dosppm_core.kernels.direct", "sample_direct_serial"))


def _child(photons: float) -> dict:
    """In the tree on sys.path: render, return seconds per timed call."""
    import importlib
    from dosppm_core.modes import sppm
    from dosppm_core.scene import builtin
    from dosppm_core.scene.loaders import load_scene
    from dosppm_core.settings import RenderSettings
    spent: dict[str, float] = {}

    def timed(name, fn):
        def call(*a, **k):
            t0 = time.perf_counter()
            try:
                return fn(*a, **k)
            finally:
                spent[name] = spent.get(name, 0.0) + time.perf_counter() - t0
        return call
    for module, name in TIMED:
        mod = importlib.import_module(module)
        if hasattr(mod, name):
            setattr(mod, name, timed(name, getattr(mod, name)))
    r = sppm.Renderer(load_scene(builtin.DEFAULT), RenderSettings())
    r.sppm.flush = timed("flush", r.sppm.flush)
    t0 = time.perf_counter()
    while r.run_iteration().photons_emitted < photons:
        pass
    return dict(spent, total=time.perf_counter() - t0, iterations=r.iteration)


def _run(tree: str, photons: float) -> dict:
    env = dict(os.environ, PYTHONPATH=tree)
    out = subprocess.run([sys.executable, "-P", os.path.abspath(__file__), "--child", str(photons)],
                         env=env, cwd=tree, check=True, capture_output=True, text=True).stdout
    return json.loads(out.strip().splitlines()[-1])


def run(args) -> dict:
    trees = {"this": ROOT, "other": os.path.abspath(args.against)}
    for tree in trees.values():        # numba's first compile, not timed
        _run(tree, 1e5)
    runs = {"this": [], "other": []}
    for i in range(args.pairs):
        for name in (("this", "other") if i % 2 == 0 else ("other", "this")):
            runs[name].append(_run(trees[name], args.photons))
    phases = [k for k in runs["this"][0] if k != "iterations" and all(k in r for r in runs["other"])]
    rows = {k: {"this_s": statistics.median(r[k] for r in runs["this"]),
                "other_s": statistics.median(r[k] for r in runs["other"]),
                "ratio": statistics.median(a[k] / b[k] for a, b in zip(runs["this"], runs["other"]) if b[k] > 0)}
            for k in phases}
    return {"scene": "built-in default", "photons": args.photons, "pairs": args.pairs,
            "other_tree_commit": _commit(trees["other"]), "rows": rows, "runs": runs}


def _commit(tree: str) -> str:
    return subprocess.run(["git", "-C", tree, "rev-parse", "HEAD"], capture_output=True, text=True).stdout.strip()


def report(res: dict) -> str:
    lines = [f"One-process SPPM, {res['scene']} scene, {res['photons']:,.0f} photons, this commit against "
             f"{res['other_tree_commit'][:10]}, {res['pairs']} alternating pairs; seconds are medians, the "
             "ratio the median of the pairs' ratios (this / other).", "",
             "| phase | this (s) | other (s) | ratio |", "|---|---|---|---|"]
    for k, r in res["rows"].items():
        lines.append(f"| `{k}` | {r['this_s']:.3f} | {r['other_s']:.3f} | {r['ratio']:.3f} |")
    return "\n".join(lines)


def main(argv=None) -> int:
    if argv is None and len(sys.argv) > 2 and sys.argv[1] == "--child":
        print(json.dumps(_child(float(sys.argv[2]))))
        return 0
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--against", required=True, help="another checkout of dosppm (a git worktree)")
    p.add_argument("--photons", type=float, default=5e6)
    p.add_argument("--pairs", type=int, default=3)
    p.add_argument("--json", default=os.path.join(ROOT, "benchmarks", "results", "sppm-phases.json"))
    args = p.parse_args(argv)
    res = run(args)
    sys.path.insert(0, ROOT)
    from harness.provenance import write_results
    write_results(args.json, res, argv)
    print(report(res))
    return 0


if __name__ == "__main__":
    sys.exit(main())
