"""Issue 33: what one texture lookup costs.

The lookup the bounce kernels and the hit points share
(`dosppm_core.kernels.texture.texel`, through its batch form
`lookup_many`), timed over many texture coordinates per call: a 1024x1024
bitmap bilinear and nearest, and a checkerboard, each at coordinates in
raster order (neighbouring lookups share cache lines, as a tile of eye
rays does) and at random ones (as photons scattered over a textured wall
are). Reported as nanoseconds per lookup, the median of the runs, beside
a loop that reads the same coordinates and returns a constant (what the
call and the loop cost without the texture).

An untextured scene performs no lookup at all (the kernels branch on the
material's texture id); that its photon and hit-point rates did not move
is measured whole-process, against the commit before textures.

    python benchmarks/texture_lookup.py [--lookups 2000000] [--repeats 7]

Writes benchmarks/results/texture-lookup.json.
"""
from __future__ import annotations

import argparse
import os
import statistics
import sys
import time

import numba as nb
import numpy as np

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, ROOT)

from dosppm_core.kernels.texture import lookup_many  # noqa: E402
from dosppm_core.scene import textures as tx  # noqa: E402
from harness.provenance import write_results  # noqa: E402

SIZE = 1024


@nb.njit(cache=True)
def _constant_many(s, r):
    """The same loop and output as `lookup_many`, with no texture read."""
    out = np.empty((s.shape[0], 3))
    for i in range(s.shape[0]):
        out[i, 0], out[i, 1], out[i, 2] = s[i] * 0.0 + 0.5, r[i] * 0.0 + 0.5, 0.5
    return out


def _textures() -> dict:
    texels = np.random.default_rng(0).uniform(0, 1, (SIZE, SIZE, 3)).astype(np.float32)
    return {"bitmap 1024x1024, bilinear": tx.bitmap("b", texels),
            "bitmap 1024x1024, nearest": tx.bitmap("n", texels, filter_type="nearest"),
            "checkerboard": tx.checkerboard("c", (0.1, 0.2, 0.3), (0.9, 0.8, 0.7))}


def _coordinates(n: int) -> dict:
    side = int(np.sqrt(n))
    s, r = np.meshgrid((np.arange(side) + 0.5) / side, (np.arange(side) + 0.5) / side)
    rng = np.random.default_rng(1)
    return {"raster order": (s.ravel(), r.ravel()),
            "random": (rng.uniform(0, 1, side * side), rng.uniform(0, 1, side * side))}


def _ns_per_lookup(fn, s, r, repeats: int) -> float:
    fn(s[:1000], r[:1000])                      # compiled (or loaded from the cache) first
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn(s, r)
        times.append(time.perf_counter() - t0)
    return 1e9 * statistics.median(times) / len(s)


def run(lookups: int, repeats: int) -> dict:
    rows = []
    for where, (s, r) in _coordinates(lookups).items():
        rows.append({"texture": "none (a constant)", "coordinates": where,
                     "ns_per_lookup": _ns_per_lookup(_constant_many, s, r, repeats)})
        for name, tex in _textures().items():
            table = tx.TextureTable.from_textures([tex])

            def fn(a, b, table=table):
                return lookup_many(table.info, table.uv_map, table.texels, 0, a, b)
            rows.append({"texture": name, "coordinates": where, "ns_per_lookup": _ns_per_lookup(fn, s, r, repeats)})
    return {"lookups": len(_coordinates(lookups)["random"][0]), "repeats": repeats, "rows": rows}


def report(res: dict) -> str:
    lines = [f"One texture lookup (`kernels.texture.texel`), {res['lookups']:,} per call, one thread, "
             f"median of {res['repeats']} calls.", "",
             "| texture | coordinates | ns per lookup | beyond the constant's loop |", "|---|---|---|---|"]
    base = {row["coordinates"]: row["ns_per_lookup"] for row in res["rows"] if row["texture"].startswith("none")}
    for row in res["rows"]:
        extra = row["ns_per_lookup"] - base[row["coordinates"]]
        lines.append(f"| {row['texture']} | {row['coordinates']} | {row['ns_per_lookup']:.1f} "
                     f"| {'-' if row['texture'].startswith('none') else f'{extra:.1f}'} |")
    return "\n".join(lines)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--lookups", type=int, default=2_000_000)
    p.add_argument("--repeats", type=int, default=7)
    p.add_argument("--json", default=os.path.join(ROOT, "benchmarks", "results", "texture-lookup.json"))
    args = p.parse_args(argv)
    res = run(args.lookups, args.repeats)
    print(report(res))
    write_results(args.json, res)
    return 0


if __name__ == "__main__":
    sys.exit(main())
