"""The bounce kernels and the hash gather alone, on recorded inputs, and the
whole photon pass (issue 11: the shared hit setup must not slow the hot
loop).

Inputs are recorded once per run from the default scene ('cornell-glass'):
- photon bounce: the first batches `trace_photon_jobs` traces, concatenated
  and intersected once; timed: `trace.scatter_photons` (the kernel plus
  its few-line wrapper);
- eye bounce: every bounce of the eye paths of a few iterations,
  concatenated; timed: `trace.advance_eye`;
- hash gather: the hit points of one eye pass and the deposits of the
  photon pass, Morton-ordered as the statistics update orders them; timed:
  `build_photon_hash` (binning and `_select_photons`) and the gather;
- photon pass: `trace_photon_jobs` over `--photons` photons, end to end.
Every input is a pure function of the scene and the seed, so two trees run
the same inputs (the checksums printed show it).

    python benchmarks/kernels.py [--label new] [--threads 2] [--fresh]

To compare two commits, copy this file into a worktree of the other and
run both copies alternately with the same --json: each run appends its
samples and medians, with the commit it ran, to benchmarks/results/kernels.json.
"""
from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import time

import numpy as np

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, ROOT)

# dosppm_core first: it sets numba's threading layer and OpenMP's wait
# policy, as in every render.
import dosppm_core
from dosppm_core import trace
from dosppm_core.accel import Accelerator
from dosppm_core.jobs import HitPoints, PhotonDeposits, RayBatch
from dosppm_core.scene import builtin
from dosppm_core.sppm.hash import build_photon_hash
from dosppm_core.sppm.statistics import initial_radius, reorder_deposits, spatial_order

# isort: split
import numba

SCENE = "cornell-glass"
SEED = 1
MAX_DEPTH = 10
PHOTONS_PER_JOB = 8192


def _git(*args: str) -> str:
    out = subprocess.run(["git", "-C", ROOT, *args], capture_output=True, text=True, check=False)
    return out.stdout.strip()


def _timed(fn, repeats: int, warmup: int = 2) -> list[float]:
    for _ in range(warmup):
        fn()
    samples = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        samples.append(time.perf_counter() - t0)
    return samples


def _jobs(scene, eps_abs, photons: int):
    for job in range(photons // PHOTONS_PER_JOB):
        yield trace.emit_photon_job(scene, SEED, job, PHOTONS_PER_JOB, eps_abs)


def _photon_bounce(scene, accel, surf, rows: int):
    """(batch, prim, u, v): the first traced batches, at least `rows` rays."""
    seen = []

    def keep(batch):
        if sum(len(b) for b in seen) < rows:
            seen.append(batch)
    trace.trace_photon_jobs(accel, surf, _jobs(scene, surf.eps_abs, 2 * rows), trace.NO_CULL,
                            MAX_DEPTH, on_batch=keep)
    batch = RayBatch.concat(seen)
    prim, _t, u, v = accel.intersect(batch.origin, batch.direction)
    return batch, prim, u, v


def _eye_bounces(scene, accel, surf, iterations: int):
    """(batch, prim, u, v) of every eye bounce of `iterations` eye passes,
    and the hit points of the first."""
    n_pix = int(scene.camera.width) * int(scene.camera.height)
    parts, first_hits = [], None
    for it in range(iterations):
        batch, hits = trace.eye_ray_job(scene, SEED, it, 0, n_pix), []
        while len(batch):
            prim, _t, u, v = accel.intersect(batch.origin, batch.direction)
            parts.append((batch, prim, u, v))
            h, _emitted, batch, _ends = trace.advance_eye(surf, batch, prim, u, v, MAX_DEPTH)
            hits.append(h)
        first_hits = first_hits if first_hits is not None else HitPoints.concat(hits)
    batch = RayBatch.concat([p[0] for p in parts])
    prim, u, v = (np.concatenate([p[k] for p in parts]) for k in (1, 2, 3))
    return (batch, prim, u, v), first_hits


def _checksum(*arrays) -> float:
    return float(sum(np.asarray(a, np.float64).sum() for a in arrays))


def _record(name, samples, results, note=""):
    med = statistics.median(samples)
    results[name] = {"median_s": med, "samples_s": samples}
    print(f"{name:24s} median {med * 1e3:9.2f} ms  (n={len(samples)}, min "
          f"{min(samples) * 1e3:.2f}, max {max(samples) * 1e3:.2f}) {note}", flush=True)


def run(args) -> dict:
    numba.set_num_threads(args.threads)
    scene = builtin.make(SCENE)
    scene.camera.width = scene.camera.height = args.eye_side
    accel = Accelerator(scene.vertices, scene.triangles, threads=args.threads)
    surf = trace.SurfaceData.from_scene(scene)
    results: dict = {}

    parts = set(args.only.split(","))
    if "bounce" in parts:
        _bounces(scene, accel, surf, args, results)
    if "pass" in parts or "hash" in parts:
        deposits = _photon_pass(scene, accel, surf, args, results, "pass" in parts)
    if "hash" in parts:
        _e, hits = _eye_bounces(scene, accel, surf, 1)
        _hash_gather(scene, surf, hits, deposits, args, results)
    accel.close()
    return results


def _bounces(scene, accel, surf, args, results) -> None:
    pb, prim, u, v = _photon_bounce(scene, accel, surf, args.bounce_rows)
    dep, nxt, _ends, _c = trace.scatter_photons(surf, pb, prim, u, v, trace.NO_CULL, MAX_DEPTH)
    print(f"photon bounce: {len(pb):,} rays, {len(dep):,} deposits, {len(nxt):,} continue, "
          f"checksum {_checksum(dep.position, nxt.origin, nxt.weight):.6e}")
    _record("scatter_photons", _timed(lambda: trace.scatter_photons(
        surf, pb, prim, u, v, trace.NO_CULL, MAX_DEPTH), args.repeats), results)

    (eb, eprim, eu, ev), _hits = _eye_bounces(scene, accel, surf, args.eye_iterations)
    h, (_lit, rgb), enxt, _e = trace.advance_eye(surf, eb, eprim, eu, ev, MAX_DEPTH)
    print(f"eye bounce: {len(eb):,} rays, {len(h):,} hit points, {len(enxt):,} continue, "
          f"checksum {_checksum(h.position, enxt.origin, rgb):.6e}")
    _record("advance_eye_paths", _timed(lambda: trace.advance_eye(
        surf, eb, eprim, eu, ev, MAX_DEPTH), args.repeats), results)


def _photon_pass(scene, accel, surf, args, results, timed: bool) -> PhotonDeposits:
    """Times the whole photon pass (if `timed`); returns its deposits."""
    out = []

    def photon_pass():
        out.append(trace.trace_photon_jobs(accel, surf, _jobs(scene, surf.eps_abs, args.photons),
                                           trace.NO_CULL, MAX_DEPTH)[0])
    if timed:
        _record("photon_pass", _timed(photon_pass, args.pass_repeats, warmup=1), results,
                f"({args.photons:,} photons)")
    else:
        photon_pass()
    deposits = out[-1]
    print(f"photon pass: {len(deposits):,} deposits, checksum {_checksum(deposits.position):.6e}")
    return deposits


def _hash_gather(scene, surf, hits, deposits: PhotonDeposits, args, results) -> None:
    """The hash build and gather of one statistics update, inputs ordered
    as `PixelStatistics.apply_photons` orders them."""
    hits = hits.take(spatial_order(hits.position))
    radius = np.full(len(hits), initial_radius(scene, hits))
    box = np.stack([hits.position.min(0) - radius[0],
                    hits.position.max(0) + radius[0]]).astype(np.float64)
    ph = reorder_deposits(deposits, box)
    table = build_photon_hash(ph, hits.position, radius, args.threads)
    m, phi = table.gather(hits, radius, surf, args.threads)
    print(f"hash: {len(hits):,} hit points, {len(ph.position):,} photons, "
          f"{len(table.count):,} kept, checksum {_checksum(m, phi):.6e}")
    _record("hash_build", _timed(lambda: build_photon_hash(ph, hits.position, radius,
                                                           args.threads), args.repeats), results)
    _record("hash_gather", _timed(lambda: table.gather(hits, radius, surf, args.threads),
                                  args.repeats), results)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--label", default="", help="a name for this run in the JSON (old, new)")
    ap.add_argument("--only", default="bounce,pass,hash",
                    help="comma-separated parts: bounce (both kernels), pass, hash")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--repeats", type=int, default=25, help="timed calls per kernel")
    ap.add_argument("--pass-repeats", type=int, default=5, help="timed photon passes")
    ap.add_argument("--photons", type=int, default=1 << 20, help="photons per photon pass")
    ap.add_argument("--bounce-rows", type=int, default=1 << 19,
                    help="recorded photon rays per timed scatter_photons call")
    ap.add_argument("--eye-side", type=int, default=512, help="eye-pass resolution (square)")
    ap.add_argument("--eye-iterations", type=int, default=4)
    ap.add_argument("--json", default=os.path.join(ROOT, "benchmarks", "results", "kernels.json"))
    ap.add_argument("--fresh", action="store_true", help="replace the JSON file's earlier runs")
    args = ap.parse_args()

    commit = _git("rev-parse", "HEAD")
    dirty = bool(_git("status", "--porcelain", "--", "dosppm_core"))
    print(f"commit {commit}{' (dosppm_core modified)' if dirty else ''}  tree {ROOT}  "
          f"label {args.label or '-'}  threads {args.threads}", flush=True)
    if os.path.dirname(os.path.abspath(dosppm_core.__file__)) != os.path.join(ROOT, "dosppm_core"):
        sys.exit(f"dosppm_core imported from {dosppm_core.__file__}, not from {ROOT}")
    results = run(args)
    run_record = {"commit": commit, "dosppm_core_modified": dirty, "label": args.label,
                  "tree": ROOT, "time": time.strftime("%Y-%m-%dT%H:%M:%S"),
                  "settings": {k: v for k, v in vars(args).items() if k not in ("json", "fresh")},
                  "results": results}
    runs = []
    if os.path.exists(args.json) and not args.fresh:
        with open(args.json) as f:
            runs = json.load(f)["runs"]
    os.makedirs(os.path.dirname(os.path.abspath(args.json)), exist_ok=True)
    with open(args.json, "w") as f:
        json.dump({"runs": runs + [run_record]}, f, indent=1)
    print(f"wrote {args.json}")


if __name__ == "__main__":
    main()
