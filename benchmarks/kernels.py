"""The bounce kernels and the gathers alone, on recorded inputs, and the
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
  `build_photon_hash` (binning and `_select_photons`) and the gather, and
  the exact grid gather (`gather_grid`, the default) of the same inputs;
- photon pass: `trace_photon_jobs` over `--photons` photons, end to end.
Every input is a pure function of the scene and the seed, so two trees run
the same inputs (the checksums printed show it).

    python benchmarks/kernels.py [--label new] [--threads 2] [--fresh]
    python benchmarks/kernels.py --against /tmp/kernels-old

Each run appends its samples and medians, with the commit it ran, to
benchmarks/results/kernels.json. Two commits can be compared by running
a copy of this file in a worktree of each, alternately; on a loaded
machine, where one run's medians differ from the next by 2x, `--against
TREE` is the steadier comparison: it loads that checkout's bounce kernels,
tracing steps and hash beside this one's, checks that both give the same
arrays, and times them call by call alternately (old, new, new, old, ...),
reporting the median of the per-pair ratios (with glibc's allocation
thresholds fixed, see `_steady_malloc`). `--against` this same tree is an
A/A run: it shows the noise floor.
"""
from __future__ import annotations

import argparse
import ctypes
import importlib.util
import json
import os
import statistics
import subprocess
import sys
import time

import numpy as np

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, ROOT)
if "--against" in sys.argv:
    # The other tree's kernels, loaded under other module names, would put
    # cache entries naming those modules into both trees' __pycache__, and
    # the next ordinary run's load fails on them (ModuleNotFoundError:
    # 'against_paths'): numba caches in a scratch folder for this run.
    import tempfile
    os.environ.setdefault("NUMBA_CACHE_DIR", tempfile.mkdtemp(prefix="dosppm-kernels-against-"))

# dosppm_core first: it sets numba's threading layer and OpenMP's wait
# policy, as in every render.
import dosppm_core
from dosppm_core import trace
from dosppm_core.accel import Accelerator
from dosppm_core.jobs import HitPoints, RayBatch
from dosppm_core.scene import builtin
from dosppm_core.sppm import grid as grid_gather
from dosppm_core.sppm import hash as hash_gather
from dosppm_core.sppm.statistics import pixel_footprint, reorder_deposits, spatial_order
from harness.provenance import provenance

# isort: split
import numba

SCENE = "cornell-glass"
SEED = 1
MAX_DEPTH = 10
PHOTONS_PER_JOB = 8192


def _git_at(tree: str, *args: str) -> str:
    out = subprocess.run(["git", "-C", tree, *args], capture_output=True, text=True, check=False)
    return out.stdout.strip()


def _git(*args: str) -> str:
    return _git_at(ROOT, *args)


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
            h, _emitted, batch, _ends, _shadows = trace.advance_eye(surf, batch, prim, u, v, MAX_DEPTH)
            hits.append(h)
        first_hits = first_hits if first_hits is not None else HitPoints.concat(hits)
    batch = RayBatch.concat([p[0] for p in parts])
    prim, u, v = (np.concatenate([p[k] for p in parts]) for k in (1, 2, 3))
    return (batch, prim, u, v), first_hits


def _flat(x) -> list:
    """The arrays in a result: nested tuples and records (of a record, its
    arrays only: PhotonHash.photons was 4 for a GatherPhotons before 88a0134)."""
    if isinstance(x, np.ndarray):
        return [x]
    if isinstance(x, (tuple, list)):
        return [a for y in x for a in _flat(y)]
    if hasattr(x, "__dict__"):
        return _flat([v for v in vars(x).values() if isinstance(v, (np.ndarray, tuple))])
    return [np.asarray(x)]


def _checksum(*arrays) -> float:
    return float(sum(np.asarray(a, np.float64).sum() for a in arrays))


def _load_against(tree: str):
    """The tracing steps, hash and grid of the checkout `tree`, loaded under
    other names beside this one's (their other imports resolve to this
    tree); its tracing steps call its own bounce kernels."""
    mods = {}
    for name, rel in (("paths", "kernels/paths.py"), ("trace", "trace.py"), ("hash", "sppm/hash.py"),
                      ("grid", "sppm/grid.py")):
        spec = importlib.util.spec_from_file_location(
            f"against_{name}", os.path.join(tree, "dosppm_core", rel))
        mod = importlib.util.module_from_spec(spec)
        sys.modules[spec.name] = mod    # dataclasses look their module up
        spec.loader.exec_module(mod)
        mods[name] = mod
    mods["trace"].paths = mods["paths"]
    return mods["trace"], mods["hash"], mods["grid"]


def _record_inputs(scene, accel, surf, args, parts) -> dict:
    inputs = {}
    if "bounce" in parts:
        inputs["photon"] = _photon_bounce(scene, accel, surf, args.bounce_rows)
        inputs["eye"] = _eye_bounces(scene, accel, surf, args.eye_iterations)[0]
        print(f"photon bounce: {len(inputs['photon'][0]):,} rays; eye bounce: "
              f"{len(inputs['eye'][0]):,} rays")
    if "hash" in parts:
        deposits = trace.trace_photon_jobs(accel, surf, _jobs(scene, surf.eps_abs, args.photons),
                                           trace.NO_CULL, MAX_DEPTH)[0]
        hits = _eye_bounces(scene, accel, surf, 1)[1]
        hits = hits.take(spatial_order(hits.position))
        radius = 3.0 * pixel_footprint(scene, hits)   # a typical fitted radius
        box = np.stack([hits.position.min(0) - radius[0],
                        hits.position.max(0) + radius[0]]).astype(np.float64)
        inputs["hash"] = (hits, radius, reorder_deposits(deposits, box))
        print(f"hash: {len(hits):,} hit points, {len(deposits):,} photons")
    return inputs


def _cases(scene, accel, surf, inputs, args, T, H, G) -> dict:
    """name -> (call, repeats) with tracing steps T, hash module H and grid G."""
    cases = {}
    if "photon" in inputs:
        pb, prim, u, v = inputs["photon"]
        eb, ep, eu, ev = inputs["eye"]
        cases["scatter_photons"] = (lambda: T.scatter_photons(surf, pb, prim, u, v, T.NO_CULL,
                                                              MAX_DEPTH), args.repeats)
        cases["advance_eye_paths"] = (lambda: T.advance_eye(surf, eb, ep, eu, ev, MAX_DEPTH),
                                      args.repeats)
    if "pass" in args.only.split(","):
        cases["photon_pass"] = (lambda: T.trace_photon_jobs(
            accel, surf, _jobs(scene, surf.eps_abs, args.photons), T.NO_CULL, MAX_DEPTH),
            args.pass_repeats)
    if "hash" in inputs:
        hits, radius, ph = inputs["hash"]
        table = H.build_photon_hash(ph, hits.position, radius, args.threads)
        cases["hash_build"] = (lambda: H.build_photon_hash(ph, hits.position, radius,
                                                           args.threads), args.repeats)
        cases["hash_gather"] = (lambda: table.gather(hits, radius, scene.materials, args.threads),
                                args.repeats)
        # The exact gather (the default), its grid built inside the call.
        cases["grid_gather"] = (lambda: G.gather_grid(ph, hits, radius, scene.materials, args.threads),
                                args.repeats)
    return cases


def _steady_malloc() -> None:
    """Fixed glibc thresholds: by default each free of a large array moves
    the mmap threshold, so whether the next call's arrays page-fault
    depends on which call ran before it (an A/A pair of identical kernels
    differed by 15%). Arrays under 32 MiB now come from a heap kept whole."""
    libc = ctypes.CDLL("libc.so.6")
    libc.mallopt(-1, 1 << 30)     # M_TRIM_THRESHOLD
    libc.mallopt(-3, 32 << 20)    # M_MMAP_THRESHOLD (fixed: no dynamic moves)


def _paired(new, old, repeats: int):
    """Samples of `new` and `old`, called alternately (old first in odd
    pairs), after one warm-up call each."""
    new(), old()
    a, b = [], []
    for r in range(repeats):
        for fn, out in ((old, b), (new, a)) if r % 2 else ((new, a), (old, b)):
            t0 = time.perf_counter()
            fn()
            out.append(time.perf_counter() - t0)
    return a, b


def run(args) -> dict:
    if args.against:
        _steady_malloc()
    numba.set_num_threads(args.threads)
    scene = builtin.make(SCENE)
    scene.camera.width = scene.camera.height = args.eye_side
    accel = Accelerator(scene.vertices, scene.triangles, threads=args.threads)
    surf = trace.SurfaceData.from_scene(scene)
    parts = set(args.only.split(","))
    inputs = _record_inputs(scene, accel, surf, args, parts)
    cases = _cases(scene, accel, surf, inputs, args, trace, hash_gather, grid_gather)
    old = {}
    if args.against:
        old_trace, old_hash, old_grid = _load_against(args.against)
        # That checkout's kernels read its own SurfaceData: the fields it has.
        fields = old_trace.paths.SurfaceData._fields
        old_surf = old_trace.paths.SurfaceData(*(getattr(surf, f) for f in fields))
        old = _cases(scene, accel, old_surf, inputs, args, old_trace, old_hash, old_grid)
    results: dict = {}
    for name, (call, repeats) in cases.items():
        out = _flat(call())
        note = f"checksum {_checksum(*out):.6e}"
        if name in old:
            same = all(np.array_equal(x, y) for x, y in zip(out, _flat(old[name][0]())))
            new_s, old_s = _paired(call, old[name][0], repeats)
            ratio = statistics.median(n / o for n, o in zip(new_s, old_s))
            results[name] = {"median_s": statistics.median(new_s), "samples_s": new_s,
                             "against": {"median_s": statistics.median(old_s), "samples_s": old_s},
                             "median_pair_ratio": ratio, "identical": same}
            note += (f"  against: median {statistics.median(old_s) * 1e3:.2f} ms, pair ratio "
                     f"{ratio:.3f}, {'identical' if same else 'DIFFERENT'}")
        else:
            new_s = _timed(call, repeats, warmup=1)
            results[name] = {"median_s": statistics.median(new_s), "samples_s": new_s}
        print(f"{name:18s} median {results[name]['median_s'] * 1e3:9.2f} ms (n={len(new_s)}) "
              f"{note}", flush=True)
    accel.close()
    return results


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
    ap.add_argument("--against", default="", help="another checkout to time call by call against")
    args = ap.parse_args()

    commit = _git("rev-parse", "HEAD")
    dirty = bool(_git("status", "--porcelain", "--", "dosppm_core"))
    print(f"commit {commit}{' (dosppm_core modified)' if dirty else ''}  tree {ROOT}  "
          f"label {args.label or '-'}  threads {args.threads}"
          f"{'  against ' + args.against if args.against else ''}", flush=True)
    if os.path.dirname(os.path.abspath(dosppm_core.__file__)) != os.path.join(ROOT, "dosppm_core"):
        sys.exit(f"dosppm_core imported from {dosppm_core.__file__}, not from {ROOT}")
    results = run(args)
    against = _git_at(args.against, "rev-parse", "HEAD") if args.against else ""
    run_record = {"commit": commit, "dosppm_core_modified": dirty, "label": args.label,
                  "against_commit": against, "tree": ROOT, "time": time.strftime("%Y-%m-%dT%H:%M:%S"),
                  "settings": {k: v for k, v in vars(args).items() if k not in ("json", "fresh")},
                  "provenance": provenance(), "results": results}
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
