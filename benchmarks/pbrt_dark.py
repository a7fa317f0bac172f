"""Issue 34: why pbrt-v4's images of our scenes came out dark.

The evaluation scored pbrt-v4 against Mitsuba 3's references and found
its images 1-34% dark, with its path tracer as with its SPPM. This
separates the causes on each scene of the failure-modes suite: pbrt's
`path` at depth 10 (issue 12's setting) and at the evaluation's depth
(ours, `harness.suites.PEER_DEPTH`), against Mitsuba's `path` with
unbounded paths (as every reference is), on the scene as it is and with
every reflectance, emission and light made the grey of its luminance
(pbrt-v4 renders spectrally: RGB colours go through its RGB-to-spectrum
upsampling, and their products differ from an RGB renderer's). What is
left on a grey scene at full depth is neither.

    DOSPPM_PBRT=path/to/pbrt python benchmarks/pbrt_dark.py [--spp 64]

Writes benchmarks/results/pbrt-dark.json (mean luminance bias of each
pbrt image against Mitsuba's at the same samples per pixel).
"""
from __future__ import annotations

import argparse
import copy
import os
import sys
import tempfile

import numpy as np

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, ROOT)

from dosppm_core.scene import builtin  # noqa: E402
from harness import metrics, pbrt  # noqa: E402
from harness.provenance import write_results  # noqa: E402
from harness.reference import render_reference  # noqa: E402
from harness.suites import PEER_DEPTH, SUITES  # noqa: E402

LUMINANCE = np.array([0.2126, 0.7152, 0.0722])
ISSUE12_DEPTH = 10


def grey(scene):
    """The scene with every colour replaced by the grey of its luminance."""
    s = copy.deepcopy(scene)
    for rgb in (s.materials.reflectance, s.materials.emission, s.lights.value):
        if len(rgb):
            rgb[:] = (np.asarray(rgb, float) @ LUMINANCE)[:, None]
    return s


def pbrt_path(scene, depth: int, spp: int, work: str) -> np.ndarray:
    world = pbrt.write_scene(scene, tempfile.mkdtemp(dir=work))
    with open(world, encoding="utf-8") as f:
        text = f.read()
    settings = pbrt.RenderSettings("path", spp, depth, int(scene.camera.width), int(scene.camera.height),
                                   pixel_filter=pbrt.pixel_filter_line(scene.camera))
    target, run = os.path.join(work, "pbrt.exr"), os.path.join(work, "run.pbrt")
    with open(run, "w", encoding="utf-8") as f:
        f.write(pbrt.with_render_settings(text, pbrt.render_directives(settings, target), os.path.dirname(world)))
    return pbrt.render(run, target, seed=7)[1]


def measure(name: str, spp: int, work: str) -> dict:
    suite = SUITES["failure-modes"]
    scene = builtin.make(name)
    scene.camera.width, scene.camera.height = suite.width, suite.height
    row = {}
    for tag, s in (("as_is", scene), ("grey", grey(scene))):
        ref = render_reference(s, spp, max_depth=-1, seed=3)
        for depth in (ISSUE12_DEPTH, PEER_DEPTH):
            row[f"{tag}_depth_{depth}"] = metrics.mean_luminance_bias(pbrt_path(s, depth, spp, work), ref)
    return row


def report(res: dict) -> str:
    d0, d1 = res["depths"]
    lines = [f"pbrt-v4 `path` against Mitsuba 3 `path` (unbounded), mean luminance bias, failure-modes scenes at "
             f"128x128, {res['spp']} spp each:", "",
             f"| scene | as is, depth {d0} | as is, depth {d1} | grey, depth {d0} | grey, depth {d1} |",
             "|---|---|---|---|---|"]
    for name, r in res["scenes"].items():
        lines.append(f"| {name} | " + " | ".join(f"{r[f'{t}_depth_{d}']:+.2%}" for t in ("as_is", "grey")
                                                  for d in (d0, d1)) + " |")
    return "\n".join(lines)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--spp", type=int, default=64)
    p.add_argument("--json", default=os.path.join(ROOT, "benchmarks", "results", "pbrt-dark.json"))
    args = p.parse_args(argv)
    if pbrt.find_binary() is None:
        print(f"pbrt_dark: {pbrt.missing_reason()}", file=sys.stderr)
        return 2
    # thin-wall's room is dark by design (the leak is the test): no mean to compare.
    names = [c.scene for c in SUITES["failure-modes"].cases if c.scene != "thin-wall"]
    with tempfile.TemporaryDirectory(prefix="dosppm-pbrt-dark-") as work:
        res = {"spp": args.spp, "depths": [ISSUE12_DEPTH, PEER_DEPTH],
               "scenes": {n: measure(n, args.spp, work) for n in names}}
    print(report(res))
    write_results(args.json, res)
    return 0


if __name__ == "__main__":
    sys.exit(main())
