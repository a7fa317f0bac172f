"""Issue 13: photons per second beside pbrt-v4's `sppm`, on the same scene
and machine, in one run.

Both render `../shared/references/sponza-point` at 320x240 with 2 threads,
100k photons per iteration and depth 10 (pbrt's settings in the accuracy
evaluation). pbrt is timed as a process at two iteration counts and its
rate is the difference (scene load and BVH build taken out); ours is SPPM
in one process, timed over whole iterations after a warm-up one. Both
compute direct light by shadow rays and trace one eye pass per iteration,
so photons/s compare like for like; hit points/s are ours only (pbrt does
not report them). Accuracy at equal time is the other half of the
comparison: `dosppm evaluate sponza` (docs/accuracy.md).

    DOSPPM_PBRT=~/.local/bin/pbrt python benchmarks/pbrt_side_by_side.py [--repeats 3]

Writes benchmarks/results/pbrt-side-by-side.json.
"""
from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, ROOT)

from dosppm_core.modes.sppm import Renderer  # noqa: E402
from dosppm_core.settings import RenderSettings  # noqa: E402
from harness import pbrt  # noqa: E402
from harness.evaluate import pbrt_sppm_radius, suite_scene  # noqa: E402
from harness.provenance import median_of, write_results  # noqa: E402
from harness.suites import SUITES  # noqa: E402

PHOTONS = 100_000
DEPTH = 10


def _pbrt_seconds(scene, world: str, iterations: int, work: str) -> float:
    settings = pbrt.RenderSettings("sppm", iterations, DEPTH, int(scene.camera.width),
                                   int(scene.camera.height), photons_per_iteration=PHOTONS,
                                   radius=pbrt_sppm_radius(scene))
    with open(world, encoding="utf-8") as f:
        text = f.read()
    target, run_file = os.path.join(work, "pbrt.exr"), os.path.join(work, "run.pbrt")
    with open(run_file, "w", encoding="utf-8") as f:
        f.write(pbrt.with_render_settings(text, pbrt.render_directives(settings, target),
                                          os.path.dirname(os.path.abspath(world))))
    return pbrt.render(run_file, target, seed=iterations)[0]


def pbrt_rate(scene, world: str, work: str, few: int, many: int) -> dict:
    t_few, t_many = _pbrt_seconds(scene, world, few, work), _pbrt_seconds(scene, world, many, work)
    return {"iterations": [few, many], "seconds": [t_few, t_many],
            "photons_per_s": (many - few) * PHOTONS / max(t_many - t_few, 1e-9)}


def our_rate(scene, iterations: int) -> dict:
    r = Renderer(scene, RenderSettings(threads=2, photons_per_iteration=PHOTONS, max_depth=DEPTH))
    try:
        r.run_iteration()                       # compile, fit the radii
        p0, t0 = r.progress(), time.perf_counter()
        for _ in range(iterations):
            r.run_iteration()
        dt, p = time.perf_counter() - t0, r.progress()
    finally:
        r.close()
    return {"iterations": iterations, "seconds": dt,
            "photons_per_s": (p.photons_emitted - p0.photons_emitted) / dt,
            "hit_points_per_s": (p.hit_points - p0.hit_points) / dt}


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--shared", default=os.path.join(ROOT, "..", "shared"))
    p.add_argument("--repeats", type=int, default=3)
    p.add_argument("--iterations", type=int, default=16, help="pbrt's longer run and ours")
    p.add_argument("--json", default=os.path.join(ROOT, "benchmarks", "results", "pbrt-side-by-side.json"))
    args = p.parse_args(argv)
    if pbrt.missing_reason():
        print(f"pbrt_side_by_side: {pbrt.missing_reason()}", file=sys.stderr)
        return 2
    suite = SUITES["sponza"]
    case = suite.cases[0]
    scene = suite_scene(suite, case, args.shared)
    world = os.path.join(args.shared, case.files.pbrt)
    ours, theirs = [], []
    with tempfile.TemporaryDirectory(prefix="dosppm-pbrt-") as work:
        for _ in range(args.repeats):          # alternated: drift hits both alike
            theirs.append(pbrt_rate(scene, world, work, 2, args.iterations))
            ours.append(our_rate(scene, args.iterations))
    res = {"scene": case.scene, "resolution": [int(scene.camera.width), int(scene.camera.height)],
           "photons_per_iteration": PHOTONS, "max_depth": DEPTH, "threads": 2,
           "pbrt_sppm": median_of(theirs), "dosppm_sppm": median_of(ours)}
    res["ratio"] = res["dosppm_sppm"]["photons_per_s"] / res["pbrt_sppm"]["photons_per_s"]
    print(f"pbrt-v4 sppm {res['pbrt_sppm']['photons_per_s']:,.0f} photons/s, dosppm "
          f"{res['dosppm_sppm']['photons_per_s']:,.0f} photons/s ({res['ratio']:.2f}x)")
    write_results(args.json, res)
    return 0


if __name__ == "__main__":
    sys.exit(main())
