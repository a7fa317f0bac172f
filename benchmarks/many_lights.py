"""Issues 12 and 30: does direct light by shadow rays pay off among
hundreds of lights? On the generated building (600 ceiling lights, about
five a room), each estimator renders for the same time twice, with two
seeds: `metrics.seed_noise` of the two images is the relMSE one render
has from noise alone (SPPM's kernel bias is the same in both and cancels),
with no reference needed. (Until issue 30's last round this file used
relmse(a, b) / 2, which divides by one seed's noisy pixel: a few pixels
decided it. It is still recorded, as `relmse_half`.)

    python benchmarks/many_lights.py [--seconds 30] [--triangles 1e6]

Estimators: the default (a shadow ray per hit point, its light from the
light tree mixed with the light cache the photons' first hits teach,
photons from their second surface on), the same with the light tree alone
(`light_cache=0`), and the paper's (every photon deposits, direct light
included). Writes benchmarks/results/many-lights.json with provenance.
"""
from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time

import numpy as np

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, ROOT)

from dosppm_core.chunks.store import ChunkStore  # noqa: E402
from dosppm_core.chunks.subdivide import subdivide  # noqa: E402
from dosppm_core.modes.osppm import OutOfCoreRenderer  # noqa: E402
from dosppm_core.scene.generate import generate_building  # noqa: E402
from dosppm_core.scene.soupfile import open_soup  # noqa: E402
from dosppm_core.settings import RenderSettings  # noqa: E402
from harness import metrics  # noqa: E402
from harness.provenance import write_results  # noqa: E402

ESTIMATORS = {"shadow rays (default: light tree + light cache)": {"direct": "nee"},
              "shadow rays, light tree alone": {"direct": "nee", "light_cache": 0},
              "photons only (the paper's)": {"direct": "photons"}}


def _photon_part(r: OutOfCoreRenderer) -> np.ndarray:
    """The photons' share of the image: eq. 5 without the eye's own terms
    (emission seen and, with shadow rays, direct light)."""
    st = r.sppm.stats
    part = st.tau / (max(st.photons_emitted, 1) * np.pi * st.radius ** 2)[:, None]
    return part.reshape(st.height, st.width, 3)


def _part_noise(pa: np.ndarray, pb: np.ndarray, a: np.ndarray, b: np.ndarray, eps: float = 1e-2) -> float:
    """The share of `metrics.seed_noise(a, b)` that parts `pa`, `pb` of the
    images carry: their squared seed difference over the whole images'
    mean (the parts' noises add, their streams being independent)."""
    m = 0.5 * (a + b)
    return float(np.mean((pa - pb) ** 2 / (2.0 * (m * m + eps))))


def _render(store_path: str, settings: dict, seed: int, seconds: float):
    """(image, its photons' part, photons, eye iterations) after `seconds`
    of iterations (the first, which loads the scene and kernels, excluded)."""
    r = OutOfCoreRenderer(ChunkStore.open(store_path), RenderSettings(seed=seed, threads=2, **settings))
    try:
        r.run_iteration()
        p0, t0 = r.progress(), time.perf_counter()
        while time.perf_counter() - t0 < seconds:
            r.run_iteration()
        r.finish()
        p1 = r.progress()
        return (r.image().copy(), _photon_part(r), p1.photons_emitted - p0.photons_emitted,
                p1.iteration - p0.iteration)
    finally:
        r.close()


def run(args) -> dict:
    work = tempfile.mkdtemp(prefix="dosppm-many-lights-")
    generate_building(os.path.join(work, "b"), triangles=int(args.triangles), lights=args.lights, seed=1,
                      width=args.width, height=args.height)
    subdivide(open_soup(os.path.join(work, "b")), os.path.join(work, "s"), chunks=1)
    rows = {}
    for name, settings in ESTIMATORS.items():
        (a, qa, pa, ia), (b, qb, pb, ib) = (_render(os.path.join(work, "s"), settings, seed, args.seconds)
                                            for seed in (1, 2))
        rows[name] = {"settings": settings, "photons": [int(pa), int(pb)], "iterations": [ia, ib],
                      "noise_relmse": metrics.seed_noise(a, b), "relmse_half": metrics.relmse(a, b) / 2,
                      "photon_part_noise": _part_noise(qa, qb, a, b),
                      "photon_part_mean": float(metrics.luminance(qa).mean() / metrics.luminance(a).mean()),
                      "mean_luminance": [float(metrics.luminance(a).mean()), float(metrics.luminance(b).mean())]}
        print(f"{name}: noise relMSE {rows[name]['noise_relmse']:.4g}, photons {pa:,}", file=sys.stderr)
    return {"scene": f"generated building, {int(args.triangles):,} triangles, {args.lights} lights, "
                     f"{args.width}x{args.height}", "seconds": args.seconds, "rows": rows}


def report(res: dict) -> str:
    lines = [f"{res['scene']}, {res['seconds']:g} s a render, two seeds each: noise = the relMSE one "
             "render has from its noise (`metrics.seed_noise` of the two).", "",
             "| estimator | photons per render | eye iterations | noise relMSE | of it, the photons' | "
             "photons' share of the image | mean luminance (seed 1, 2) |",
             "|---|---|---|---|---|---|---|"]
    for name, r in res["rows"].items():
        lines.append(f"| {name} | {r['photons'][0]:,} | {r['iterations'][0]} | {r['noise_relmse']:.4g} | "
                     f"{r.get('photon_part_noise', float('nan')):.4g} | {r.get('photon_part_mean', float('nan')):.0%} | "
                     f"{r['mean_luminance'][0]:.4g}, {r['mean_luminance'][1]:.4g} |")
    paper = next((r for name, r in res["rows"].items() if name.startswith("photons only")), None)
    if paper:
        lines += ["", "Noise at equal time against the photons-only estimator's: " + ", ".join(
            f"{name} {r['noise_relmse'] / paper['noise_relmse']:.2f}x" for name, r in res["rows"].items()
            if r is not paper) + "."]
        default = next(iter(res["rows"].values()))
        if "photon_part_noise" in default:
            # However well the shadow ray's light is chosen, the photons'
            # (indirect) part of the default stays: the light choice cannot
            # take the default below it.
            lines += [f"The default's photons alone (indirect light) carry noise "
                      f"{default['photon_part_noise'] / paper['noise_relmse']:.2f}x the photons-only estimator's "
                      "whole noise: no light choice takes the default below that."]
    return "\n".join(lines)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--seconds", type=float, default=30.0)
    p.add_argument("--triangles", type=float, default=1e6)
    p.add_argument("--lights", type=int, default=600)
    p.add_argument("--width", type=int, default=192)
    p.add_argument("--height", type=int, default=144)
    p.add_argument("--json", default=os.path.join(ROOT, "benchmarks", "results", "many-lights.json"))
    args = p.parse_args(argv)
    res = run(args)
    print(report(res))
    write_results(args.json, res)
    return 0


if __name__ == "__main__":
    sys.exit(main())
