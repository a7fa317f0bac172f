"""Issue 3's benchmark: OSPPM throughput against the number of chunks (the
paper's Figure 11) and subdivision / load / BVH-build times (its Table 1).

For each scene and c in CHUNKS, in one run:
- subdivide with `--chunks c` (seconds);
- load every chunk and build its BVH (median seconds per chunk);
- render OSPPM iterations and report photons/s and hit points/s, median of
  the timed iterations after one warm-up, twice: with every chunk resident,
  and with memory for only the two largest chunks (the active one and the
  one prefetched), which is what a scene larger than memory forces.

    python benchmarks/osppm.py [--building-triangles 10M] [--iterations 3]

Writes benchmarks/results/osppm.json and prints a Markdown table.
"""
from __future__ import annotations

import argparse
import json
import os
import shutil
import statistics
import sys
import tempfile
import time

import numpy as np

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, ROOT)

from dosppm_core.chunks.store import ChunkStore  # noqa: E402
from dosppm_core.chunks.subdivide import subdivide  # noqa: E402
from dosppm_core.chunks.view import ChunkView  # noqa: E402
from dosppm_core.modes.osppm import OutOfCoreRenderer  # noqa: E402
from dosppm_core.scene import builtin  # noqa: E402
from dosppm_core.scene.generate import generate_building  # noqa: E402
from dosppm_core.scene.soup import SceneSource  # noqa: E402
from dosppm_core.scene.soupfile import open_soup  # noqa: E402
from dosppm_core.settings import RenderSettings  # noqa: E402
from harness.provenance import write_results  # noqa: E402

CHUNKS = (1, 2, 4, 8, 16)
DRAGON = os.path.join(ROOT, "..", "shared", "scenes", "stanford_dragon", "dragon_100k.ply")


def _sources(args, work: str):
    out = []
    if os.path.exists(DRAGON):
        out.append(("dragon in Cornell box", SceneSource(builtin.cornell_with_mesh(DRAGON))))
    else:
        out.append(("cornell-glass", SceneSource(builtin.make("cornell-glass"))))
    if args.building_triangles:
        path = os.path.join(work, "building")
        t0 = time.perf_counter()
        generate_building(path, triangles=args.building_triangles, lights=args.lights, seed=1)
        print(f"generated building ({args.building_triangles:,} triangles) in "
              f"{time.perf_counter() - t0:.0f} s", file=sys.stderr)
        out.append((f"building {args.building_triangles / 1e6:.0f}M", open_soup(path)))
    return out


def _load_times(store: ChunkStore) -> list[float]:
    times = []
    for k in range(store.chunk_count):
        t0 = time.perf_counter()
        view = ChunkView(k, store.load(k), store.header, store.tree, threads=2)
        times.append(time.perf_counter() - t0)
        view.close()
    return times


def _throughput(store: ChunkStore, settings: RenderSettings, memory, iterations: int) -> dict:
    r = OutOfCoreRenderer(store, settings, memory_bytes=memory)
    try:
        r.run_iteration()       # warm-up: compile, radii, first loads
        per_iter = []
        for _ in range(iterations):
            p0, t0 = r.progress(), time.perf_counter()
            r.run_iteration()
            per_iter.append((time.perf_counter() - t0, r.progress().photons_emitted - p0.photons_emitted))
        r.finish()
        c = r.cache.counters
        # Photons per second of whole iterations (eye tracing, loads and
        # statistics updates included): what a user gets.
        return {"photons_per_s": statistics.median(n / dt for dt, n in per_iter),
                "hit_points_per_eye_s": r.hit_point_total / max(r.phase_seconds["eye"], 1e-9),
                "phase_seconds": dict(r.phase_seconds), "loads": c.loads,
                "activations": c.activations, "portal_rays": c.portal_rays,
                "wait_seconds": c.wait_seconds, "load_seconds": c.load_seconds}
    finally:
        r.close()


def main() -> int:
    p = argparse.ArgumentParser()
    p.add_argument("--building-triangles", type=float, default=10e6)
    p.add_argument("--lights", type=int, default=600)
    p.add_argument("--iterations", type=int, default=3)
    p.add_argument("--photons", type=int, default=1_000_000, help="photons per iteration")
    p.add_argument("--chunks", type=int, nargs="*", default=list(CHUNKS))
    p.add_argument("--out", default=os.path.join(ROOT, "benchmarks", "results", "osppm.json"))
    args = p.parse_args()
    args.building_triangles = int(args.building_triangles)
    settings = RenderSettings(seed=1, photons_per_iteration=args.photons, threads=2)
    results = []
    with tempfile.TemporaryDirectory(prefix="dosppm-bench-") as work:
        for name, source in _sources(args, work):
            for c in args.chunks:
                path = os.path.join(work, f"store-{len(results)}")
                t0 = time.perf_counter()
                subdivide(source, path, chunks=c)
                t_sub = time.perf_counter() - t0
                store = ChunkStore.open(path)
                loads = _load_times(store)
                row = {"scene": name, "triangles": int(source.count), "chunks": c,
                       "stored_triangles": int(store.chunk_triangles.sum()),
                       "subdivide_s": t_sub, "load_build_s_median": statistics.median(loads),
                       "load_build_s_max": max(loads)}
                for label, memory in (("all", None),
                                      ("two", float(np.sort(store.chunk_memory)[-2:].sum())
                                       if c > 1 else None)):
                    row[label] = _throughput(store, settings, memory, args.iterations)
                print(json.dumps(row), file=sys.stderr)
                results.append(row)
                shutil.rmtree(path)
    print(report(results))
    write_results(args.out, {"rows": results})
    return 0


def report(results: list[dict]) -> str:
    """The Figure 11 / Table 1 table, in Markdown."""
    lines = ["| scene | c | duplicated | subdivide s | load+BVH s/chunk | photons/s (all resident) "
             "| vs c=1 | photons/s (2 resident) | vs c=1 | hit points per eye-tracing s (all) | vs c=1 |",
             "|---|---|---|---|---|---|---|---|---|---|---|"]
    base = {}
    for r in results:
        b = base.setdefault(r["scene"], r)
        dup = r["stored_triangles"] / r["triangles"] - 1
        lines.append(
            f"| {r['scene']} | {r['chunks']} | {dup:.1%} | {r['subdivide_s']:.1f} "
            f"| {r['load_build_s_median']:.3f} "
            f"| {r['all']['photons_per_s']:,.0f} | {r['all']['photons_per_s'] / b['all']['photons_per_s']:.2f} "
            f"| {r['two']['photons_per_s']:,.0f} | {r['two']['photons_per_s'] / b['all']['photons_per_s']:.2f} "
            f"| {r['all']['hit_points_per_eye_s']:,.0f} "
            f"| {r['all']['hit_points_per_eye_s'] / b['all']['hit_points_per_eye_s']:.2f} |")
    return "\n".join(lines)


if __name__ == "__main__":
    sys.exit(main())
