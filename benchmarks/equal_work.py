"""Issue 13: the four ways to run, at equal work, on the same 2 cores.

SPPM in one process, OSPPM (one process, the scene in chunks), and DOSPPM
with one and two tracer processes (two also gathering at the tracers) render the same scene for the same time
with the same photons per iteration: one eye pass, and so one hit point
per pixel that sees a surface, per PHOTONS photons, and statistics updated
per PHOTONS deposits at most. What each then delivers is reported side by
side: photons/s and hit points/s, and hit points per photon, which shows
whether the eye rate really matched (DOSPPM starts an eye pass per PHOTONS
photons emitted, but never more than 16 in flight, so it may do fewer).

    python benchmarks/equal_work.py [--seconds 20] [--repeats 3] [--photons 1000000]

Writes benchmarks/results/equal-work.json (every run, with provenance) and
prints the table. Equal error at equal time is `dosppm evaluate sponza`.
"""
from __future__ import annotations

import argparse
import os
import sys
import tempfile

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, ROOT)
sys.path.insert(0, os.path.join(ROOT, "benchmarks"))

import dosppm as service_bench  # noqa: E402
from dosppm_core.chunks.subdivide import open_or_subdivide  # noqa: E402
from dosppm_core.modes.osppm import OutOfCoreRenderer  # noqa: E402
from dosppm_core.modes.sppm import Renderer  # noqa: E402
from dosppm_core.scene.soup import SceneSource  # noqa: E402
from dosppm_core.settings import RenderSettings  # noqa: E402
from harness.provenance import median_of, write_results  # noqa: E402


def run(args) -> dict:
    work = tempfile.mkdtemp(prefix="dosppm-equal-work-")
    name, scene = service_bench._scene(args, work)
    stores = {c: open_or_subdivide(SceneSource(scene), os.path.join(work, "stores"), chunks=c)
              for c in (1, args.chunks)}
    settings = RenderSettings(threads=2, photons_per_iteration=args.photons, photon_batch=args.photons)
    same = ["--photons-per-iteration", str(args.photons), "--photon-batch", str(args.photons)]
    configs = {
        "SPPM, one process": lambda: service_bench._single(lambda: Renderer(scene, settings), args.seconds),
        f"OSPPM c = {args.chunks}, one process": lambda: service_bench._single(
            lambda: OutOfCoreRenderer(stores[args.chunks], settings), args.seconds),
        "DOSPPM c = 1, n = 1": lambda: service_bench._dosppm(stores[1].path, 1, args.seconds, work, same),
        "DOSPPM c = 1, n = 2": lambda: service_bench._dosppm(stores[1].path, 2, args.seconds, work, same),
        # Issue 32's way: tracers make the photons and gather them by epochs.
        "DOSPPM c = 1, n = 2, gather at the tracers": lambda: service_bench._dosppm(
            stores[1].path, 2, args.seconds, work, same + ["--gather-at", "tracers"]),
    }
    runs = {}
    for _ in range(args.repeats):       # interleaved: drift on a shared machine hits every row alike
        for key, fn in configs.items():
            r = fn()
            r["hit_points_per_photon"] = r["hit_points_per_s"] / max(r["photons_per_s"], 1e-9)
            runs.setdefault(key, []).append(r)
            print(f"{key}: {r['photons_per_s']:,.0f} photons/s, {r['hit_points_per_s']:,.0f} hit points/s",
                  file=sys.stderr)
    return {"scene": name, "triangles": scene.triangle_count, "seconds": args.seconds,
            "photons_per_iteration": args.photons, "runs": {k: median_of(v) for k, v in runs.items()}}


def report(res: dict) -> str:
    R = res["runs"]
    base = next(iter(R.values()))
    lines = [f"Equal work: {res['scene']} ({res['triangles']:,} triangles), {res['photons_per_iteration']:,} "
             f"photons per iteration and per statistics update in every mode, {res['seconds']:.0f} s a run, "
             f"medians of {base['repeats']}.", "",
             "| configuration | photons/s | vs SPPM | hit points/s | vs SPPM | hit points per photon | iterations |",
             "|---|---|---|---|---|---|---|"]
    for key, r in R.items():
        lines.append(f"| {key} | {r['photons_per_s']:,.0f} | {r['photons_per_s'] / base['photons_per_s']:.2f} "
                     f"| {r['hit_points_per_s']:,.0f} | {r['hit_points_per_s'] / base['hit_points_per_s']:.2f} "
                     f"| {r['hit_points_per_photon']:.3f} | {r['iterations']:.0f} |")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--seconds", type=float, default=20.0)
    p.add_argument("--repeats", type=int, default=3)
    p.add_argument("--photons", type=int, default=1_000_000, help="photons per iteration, every mode")
    p.add_argument("--chunks", type=int, default=4, help="OSPPM's chunks")
    p.add_argument("--json", default=os.path.join(ROOT, "benchmarks", "results", "equal-work.json"))
    args = p.parse_args(argv)
    res = run(args)
    print(report(res))
    write_results(args.json, res)
    return 0


if __name__ == "__main__":
    sys.exit(main())
