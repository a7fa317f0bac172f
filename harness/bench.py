"""`dosppm bench`: throughput of the core pipeline, measured side by side in
one run, beside the paper's Table 4 (Günther & Grosch, one 2010 CPU thread
and a GTX 460).

Reported per scene (medians of `repeats` runs):
- raw Embree closest-hit rays/s on exactly the rays our photon paths trace
  (the limit), our photon rays/s through the whole step (emission,
  intersection, scattering, deposits, compaction) and their ratio;
- photon paths/s and hit points/s (eye passes);
- the statistics update per 1M deposited photons for each gather, with and
  without Morton reordering.
"""
from __future__ import annotations

import copy
import math
import statistics
import time

import numpy as np

from dosppm_core.modes.sppm import Renderer
from dosppm_core.settings import RenderSettings
from dosppm_core.trace import NO_CULL, emit_photon_job, trace_photon_jobs
from harness.provenance import write_results

PAPER_HIT_POINTS = 640_000      # Table 4's statistics update was measured at 640k hit points
PAPER_TABLE4 = {
    "photon_tracing_ms_per_100k_photons_cpu_1thread": 2633.1,
    "hit_point_tracing_ms_per_640k_cpu_1thread": 3659.7,
    "statistics_update_ms_per_1M_cpu_1thread": 792.5,
    "statistics_update_ms_per_1M_gpu_gtx460": 18.4,
}


def _median_time(fn, repeats: int, samples: list | None = None) -> float:
    """The median of `repeats` timings of fn(); each timing is appended to
    `samples` (the results file keeps every run, not only the median)."""
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    if samples is not None:
        samples.extend(times)
    return statistics.median(times)


def _photon_rays(r: Renderer, photons: int, job0: int):
    """Trace `photons` photons as the renderer does; returns (deposits,
    emitted paths, the (origin, direction) of every traced batch)."""
    s = r.settings
    batches = []
    jobs = (emit_photon_job(r.scene, s.seed, job0 + k, min(s.photons_per_job, photons - done),
                            r.surf.eps_abs)
            for k, done in enumerate(range(0, photons, s.photons_per_job)))
    deposits, _ends, _culled = trace_photon_jobs(
        r.accel, r.surf, jobs, NO_CULL, s.max_depth, deposit_from=s.deposit_from,
        on_batch=lambda b: batches.append((b.origin, b.direction)))
    return deposits, photons, batches


def bench_scene(scene, photons: int = 1_000_000, repeats: int = 3, threads: int = 2,
                paper_hit_points: int = PAPER_HIT_POINTS) -> dict:
    r = Renderer(scene, RenderSettings(threads=threads, photons_per_iteration=50_000))
    for _ in range(3):      # compile, then let radii shrink to working size
        r.run_iteration()
    out = {"scene": scene.name, "triangles": scene.triangle_count,
           "resolution": [int(scene.camera.width), int(scene.camera.height)]}
    seconds = out["samples_s"] = {}     # every timing, by figure
    # Photon tracing, whole pipeline vs raw Embree on the same rays.
    t_ours = _median_time(lambda: _photon_rays(r, photons, 10_000), repeats,
                          seconds.setdefault("photon_pass", []))
    deposits, emitted, batches = _photon_rays(r, photons, 10_000)
    rays = sum(len(o) for o, _ in batches)
    t_raw = _median_time(lambda: [r.accel.intersect(o, d) for o, d in batches], repeats,
                         seconds.setdefault("raw_embree", []))
    out.update(photon_rays=rays, photon_rays_per_s=rays / t_ours, raw_embree_rays_per_s=rays / t_raw,
               ratio_to_raw=t_raw / t_ours, photon_paths_per_s=emitted / t_ours,
               deposits_per_photon=len(deposits) / emitted)
    n_pix = int(scene.camera.width) * int(scene.camera.height)
    t_eye = _median_time(r._eye_pass, repeats, seconds.setdefault("eye_pass", []))
    out["hit_points_per_s"] = len(r.stats.hit_points) / t_eye
    out["eye_rays_per_s"] = n_pix / t_eye
    # Statistics update per 1M deposits, each gather, with/without reordering.
    batch = deposits.take(np.arange(min(len(deposits), 1_000_000)))
    out["update_deposits"] = len(batch)
    out["hit_points"] = len(r.stats.hit_points)
    for gather in ("grid", "hash"):
        for reorder in (True, False):
            name = f"update_ms_per_1M_{gather}_{'sorted' if reorder else 'unsorted'}"
            out[name] = _update_ms(r, batch, gather, reorder, repeats, seconds.setdefault(name, []))
    out.update(_update_parts(r, batch, repeats, seconds))
    # Per emitted photon, the unit a render's throughput is quoted in.
    out["update_ms_per_1M_emitted_grid_sorted"] = (out["update_ms_per_1M_grid_sorted"]
                                                   * out["deposits_per_photon"])
    r.close()
    # The same deposits at the paper's 640k hit points (Table 4's setting).
    big = _at_hit_points(scene, paper_hit_points, threads)
    out["hit_points_paper"] = len(big.stats.hit_points)
    out["update_ms_per_1M_grid_sorted_paper_hit_points"] = _update_ms(
        big, batch, "grid", True, repeats, seconds.setdefault("update_paper_hit_points", []))
    big.close()
    return out


def _update_ms(r: Renderer, batch, gather: str, reorder: bool, repeats: int, samples: list) -> float:
    """Median ms of one statistics update of `batch`, per 1M deposits; the
    statistics are restored after each, so every repeat does the same work."""
    def update():
        s = r.stats
        saved = (s.photon_count.copy(), s.radius.copy(), s.tau.copy(), s.photons_emitted)
        s.apply_photons(batch, 0, r.scene.materials, gather=gather, threads=r.settings.threads,
                        reorder=reorder)
        s.photon_count, s.radius, s.tau, s.photons_emitted = saved
    update()   # compile
    return 1e3 * _median_time(update, repeats, samples) * 1e6 / max(len(batch), 1)


def _update_parts(r: Renderer, batch, repeats: int, seconds: dict) -> dict:
    """The grid update's parts, each timed alone, ms per 1M deposits: the
    photons' reordering and the hit points' grid (which overlap in an
    update: the grid is built on a second thread) and the gather."""
    from dosppm_core.sppm.grid import build_hit_point_grid, gather_grid
    from dosppm_core.sppm.statistics import reorder_deposits
    st, mats, threads = r.stats, r.scene.materials, r.settings.threads
    hp, radius, box = st.hit_points, st.radius[st.hit_points.pixel], st.gather_box()
    grid = build_hit_point_grid(hp, radius, mats)
    photons = reorder_deposits(batch, box, threads)
    parts = {"reorder": lambda: reorder_deposits(batch, box, threads),
             "grid_build": lambda: build_hit_point_grid(hp, radius, mats),
             "gather": lambda: gather_grid(photons, hp, radius, mats, threads, grid)}
    per = 1e3 * 1e6 / max(len(batch), 1)
    return {f"update_part_ms_per_1M_{name}": per * _median_time(fn, repeats, seconds.setdefault(name, []))
            for name, fn in parts.items()}


def _at_hit_points(scene, hit_points: int, threads: int) -> Renderer:
    """A renderer of `scene` at the resolution that gives about `hit_points`
    hit points, warmed up as bench_scene's is."""
    probe = Renderer(scene, RenderSettings(threads=threads, photons_per_iteration=50_000))
    probe.run_iteration()
    share = len(probe.stats.hit_points) / (scene.camera.width * scene.camera.height)
    probe.close()
    big = copy.deepcopy(scene)
    scale = math.sqrt(hit_points / max(share, 1e-6) / (scene.camera.width * scene.camera.height))
    big.camera.width = max(1, round(scene.camera.width * scale))
    big.camera.height = max(1, round(scene.camera.height * scale))
    r = Renderer(big, RenderSettings(threads=threads, photons_per_iteration=50_000))
    for _ in range(3):
        r.run_iteration()
    return r


def report(results: list[dict]) -> str:
    lines = ["| figure | " + " | ".join(r["scene"] for r in results) + " | paper (Table 4) |",
             "|---|" + "---|" * len(results) + "---|"]
    rows = [
        ("triangles", "triangles", "{:,}", ""),
        ("raw Embree rays/s (same rays)", "raw_embree_rays_per_s", "{:,.0f}", ""),
        ("our photon rays/s", "photon_rays_per_s", "{:,.0f}", ""),
        ("ratio to raw (target >= 0.5)", "ratio_to_raw", "{:.2f}", ""),
        ("photon paths/s", "photon_paths_per_s", "{:,.0f}",
         f"{1e5 / PAPER_TABLE4['photon_tracing_ms_per_100k_photons_cpu_1thread'] * 1e3:,.0f} (1 thread)"),
        ("hit points in an update", "hit_points", "{:,}", "640,000"),
        ("hit points/s", "hit_points_per_s", "{:,.0f}",
         f"{640e3 / PAPER_TABLE4['hit_point_tracing_ms_per_640k_cpu_1thread'] * 1e3:,.0f} (1 thread)"),
        ("update ms per 1M deposits, grid, sorted (target <= 50)", "update_ms_per_1M_grid_sorted", "{:.0f}", ""),
        ("... of which gather (alone)", "update_part_ms_per_1M_gather", "{:.0f}", ""),
        ("... of which photon reordering (alone, 2 threads)", "update_part_ms_per_1M_reorder", "{:.0f}", ""),
        ("... of which hit-point grid (alone, overlaps the reordering)", "update_part_ms_per_1M_grid_build",
         "{:.0f}", ""),
        ("... grid, unsorted", "update_ms_per_1M_grid_unsorted", "{:.0f}", ""),
        ("... grid, sorted, at the paper's 640k hit points", "update_ms_per_1M_grid_sorted_paper_hit_points",
         "{:.0f}", "792.5 CPU / 18.4 GPU"),
        ("... grid, sorted, per 1M emitted photons", "update_ms_per_1M_emitted_grid_sorted", "{:.0f}", ""),
        ("... hash, sorted", "update_ms_per_1M_hash_sorted", "{:.0f}", ""),
        ("... hash, unsorted", "update_ms_per_1M_hash_unsorted", "{:.0f}", ""),
    ]
    for title, key, fmt, paper in rows:
        cells = [fmt.format(r[key]) if key in r else "-" for r in results]
        lines.append(f"| {title} | " + " | ".join(cells) + f" | {paper} |")
    return "\n".join(lines)


def write_json(path: str, results: list[dict]) -> None:
    """The results with their provenance (commit, date, machine, command)."""
    write_results(path, {"paper_table4": PAPER_TABLE4, "results": results})
