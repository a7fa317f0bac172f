"""Eye passes and photon passes per second of one process (SPPM, the whole
scene), on the generated building with hundreds of lights: hit points per
second of eye pass, photons per second of photon pass, and the share of an
iteration each takes, at the default photons per iteration.

    python benchmarks/eye_pass.py [--iterations 30] [--repeats 3] [--code DIR]

`--base DIR` runs another checkout's dosppm_core (a worktree of an older
commit) and this one's side by side, alternating round by round, and
reports each one's medians and their ratio:

    git worktree add /tmp/base e4ef81a
    python benchmarks/eye_pass.py --base /tmp/base

(`--code DIR` measures only that checkout.)

Writes benchmarks/results/eye-pass.json with provenance.
"""
from __future__ import annotations

import argparse
import os
import statistics
import subprocess
import sys
import time

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def measure(args) -> dict:
    """One run: the median eye and photon pass over --iterations (the first
    iteration, which loads kernels and fits radii, left out)."""
    from dosppm_core.modes.sppm import Renderer
    from dosppm_core.scene.generate import building_scene
    from dosppm_core.settings import RenderSettings
    scene = building_scene(int(args.triangles), args.lights, floors=2, seed=1, width=args.width,
                           height=args.height)
    r = Renderer(scene, RenderSettings(seed=1, threads=2, direct=args.direct))
    r.run_iteration()
    eye, photons = [], []
    for _ in range(args.iterations):
        t0 = time.perf_counter()
        r._eye_pass()
        t1 = time.perf_counter()
        r._photon_pass(None)
        r.sppm.flush()
        r.iteration += 1
        eye.append(t1 - t0)
        photons.append(time.perf_counter() - t1)
    r.close()
    e, p = statistics.median(eye), statistics.median(photons)
    pixels = args.width * args.height
    return {"eye_s": e, "photon_s": p, "hit_points_per_eye_s": pixels / e,
            "photons_per_photon_s": r.settings.photons_per_iteration / p, "eye_share": e / (e + p),
            "photons_per_iteration": r.settings.photons_per_iteration}


def report(res: dict) -> str:
    rows = [("base", f"base ({res.get('base_commit', '?')[:7]})"), ("this", "this commit")]
    lines = [f"{res['scene']}, medians of {len(res['runs']['this'])} runs a side, alternating:", "",
             "| code | eye pass (ms) | hit points / eye-second | photon pass (ms) | eye share of an iteration |",
             "|---|---|---|---|---|"]
    for key, name in rows:
        if key in res["median"]:
            m = res["median"][key]
            lines.append(f"| {name} | {m['eye_s'] * 1e3:.1f} | {m['hit_points_per_eye_s']:,.0f} | "
                         f"{m['photon_s'] * 1e3:.1f} | {m['eye_share']:.0%} |")
    if "ratio_this_to_base" in res:
        r = res["ratio_this_to_base"]
        lines += ["", f"Hit points per eye-second {r['hit_points_per_eye_s']:.1f}x the base's; "
                      f"photons per photon-second {r['photons_per_photon_s']:.2f}x."]
    return "\n".join(lines)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--iterations", type=int, default=30)
    p.add_argument("--repeats", type=int, default=3)
    p.add_argument("--triangles", type=float, default=2e6)
    p.add_argument("--lights", type=int, default=300)
    p.add_argument("--width", type=int, default=160)
    p.add_argument("--height", type=int, default=120)
    p.add_argument("--direct", default="nee")
    p.add_argument("--code", default=None, help="a checkout whose dosppm_core to measure")
    p.add_argument("--base", default=None, help="a checkout to measure beside this one, round by round")
    p.add_argument("--one", action="store_true", help=argparse.SUPPRESS)   # a child's single run
    p.add_argument("--json", default=os.path.join(ROOT, "benchmarks", "results", "eye-pass.json"))
    args = p.parse_args(argv)
    if args.one:
        import json
        sys.path.insert(0, args.code or ROOT)
        print(json.dumps(measure(args)))
        return 0
    import json
    child = ["--iterations", str(args.iterations), "--triangles", str(args.triangles), "--lights",
             str(args.lights), "--width", str(args.width), "--height", str(args.height), "--direct", args.direct]

    def one(code):
        # Each run in its own process (python -P: the --code tree, not this one).
        out = subprocess.run([sys.executable, "-P", os.path.abspath(__file__), *child, "--code", code, "--one"],
                             check=True, capture_output=True, text=True).stdout
        run = json.loads(out.strip().splitlines()[-1])
        print(code, run, file=sys.stderr)
        return run

    codes = {"base": args.base, "this": args.code or ROOT} if args.base else {"this": args.code or ROOT}
    runs = {name: [] for name in codes}
    for _ in range(args.repeats):
        for name, code in codes.items():
            runs[name].append(one(code))
    median = {name: {k: statistics.median(r[k] for r in rs) for k in rs[0]} for name, rs in runs.items()}
    res = {"scene": f"generated building, {int(args.triangles):,} triangles, {args.lights} lights, "
                    f"{args.width}x{args.height}, SPPM, direct {args.direct}",
           "code": {name: os.path.abspath(code) for name, code in codes.items()}, "runs": runs, "median": median}
    if args.base:
        res["base_commit"] = subprocess.run(["git", "-C", args.base, "rev-parse", "HEAD"], capture_output=True,
                                            text=True).stdout.strip()
        res["ratio_this_to_base"] = {k: median["this"][k] / median["base"][k]
                                     for k in ("hit_points_per_eye_s", "photons_per_photon_s")}
    sys.path.insert(0, ROOT)
    from harness.provenance import write_results
    write_results(args.json, res)
    print(report(res))
    return 0


if __name__ == "__main__":
    sys.exit(main())
