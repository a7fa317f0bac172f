"""Issue 13: photon paths per second of the README's main job, `dosppm
render --time 30` on the built-in default scene, as the render's own JSON
reports them, with hit points per second beside them and where the two
cores went (the server's CPU and the tracers' busy share).

    python benchmarks/render_default.py [--seconds 30] [--repeats 3]

Writes benchmarks/results/render-default.json.
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, ROOT)

from harness.provenance import median_of, write_results  # noqa: E402


def one(seconds: float, work: str) -> dict:
    out = os.path.join(work, "render.exr")
    subprocess.run([sys.executable, "-m", "services.cli", "render", "--time", str(seconds), "--out", out,
                    "--http", "off", "--quiet"], cwd=ROOT, check=True, timeout=seconds * 10 + 300)
    with open(os.path.splitext(out)[0] + ".json", encoding="utf-8") as f:
        s = json.load(f)
    secs, tr = s["seconds"], s["tracers"]
    return {"seconds": secs, "photons_per_s": s["counters"]["photons_committed"] / secs,
            "hit_points_per_s": s["hit_points"] / secs, "iterations": s["iteration"],
            "server_cpu_load": s.get("cpu_s", 0.0) / secs,
            "tracer_busy": sum(t.get("busy_s", 0.0) for t in tr) / secs / max(len(tr), 1),
            "tracers": len(tr)}


def report(res: dict) -> str:
    r = res["render"]
    return "\n".join([
        f"`dosppm render --time {res['seconds']:.0f}` on the default scene, this 2-core machine, "
        f"medians of {r['repeats']}.", "",
        "| photons/s (target >= 1M) | hit points/s | eye iterations | server CPU (cores) | tracers busy |",
        "|---|---|---|---|---|",
        f"| {r['photons_per_s']:,.0f} | {r['hit_points_per_s']:,.0f} | {r['iterations']:.0f} | "
        f"{r['server_cpu_load']:.2f} | {r['tracer_busy']:.0%} of {r['tracers']:.0f} |"])


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--seconds", type=float, default=30.0)
    p.add_argument("--repeats", type=int, default=3)
    p.add_argument("--json", default=os.path.join(ROOT, "benchmarks", "results", "render-default.json"))
    args = p.parse_args(argv)
    with tempfile.TemporaryDirectory(prefix="dosppm-render-") as work:
        runs = [one(args.seconds, work) for _ in range(args.repeats)]
    res = {"seconds": args.seconds, "render": median_of(runs)}
    print(report(res))
    write_results(args.json, res)
    return 0


if __name__ == "__main__":
    sys.exit(main())
