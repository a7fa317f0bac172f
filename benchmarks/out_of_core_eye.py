"""Issue 31: do eye passes keep up out of core? The generated building
(5M triangles, 200 lights) is subdivided at a 128 MiB budget (8 chunks)
and rendered for the same time in four ways, side by side in one run:

- DOSPPM, 2 tracers, out of core (`--memory`, 100 MiB each);
- DOSPPM, 2 tracers, every chunk resident (the default memory);
- OSPPM, out of core (`--memory` room for two chunks);
- OSPPM, every chunk resident.

Each run records photons emitted, eye iterations, hit points per second
and, for DOSPPM, the status page's timeline: the share of the photons
emitted so far that is committed half-way through (a job's deposits
count once its last path has ended), and each tracer's seconds by what it
did. With pbrt-v4 at hand (DOSPPM_PBRT), each image's relMSE against a
converged pbrt-v4 `path` reference of the same building (--reference-spp
samples a pixel, cached in --cache; about 40 minutes on 2 cores). The
building's tinted glass is made grey in both (pbrt-v4 has no tinted
dielectric), as in many_lights_pbrt.py.

    DOSPPM_PBRT=~/.cache/pbrt-v4/build/pbrt python benchmarks/out_of_core_eye.py [--seconds 30] [--repeats 1]

The scene is generated once into --work (about 3 minutes, 1.5 GB).
"""
from __future__ import annotations

import argparse
import json
import os
import socket
import statistics
import subprocess
import sys
import time
import urllib.request

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, ROOT)

import numpy as np  # noqa: E402

from dosppm_core.chunks.store import ChunkStore  # noqa: E402
from dosppm_core.film import read_exr  # noqa: E402
from dosppm_core.scene.generate import building_scene  # noqa: E402
from dosppm_core.scene.soupfile import SoupWriter, open_soup  # noqa: E402
from many_lights_pbrt import pbrt_reference, score  # noqa: E402
from harness import pbrt  # noqa: E402
from harness.provenance import write_results  # noqa: E402

WORK = os.path.join(os.path.expanduser("~"), ".cache", "dosppm", "bench", "building-5M-grey")


def _dosppm(*args: str, **kw) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-P", "-m", "services.cli", *args], cwd=ROOT, check=True,
                          env=dict(os.environ, PYTHONPATH=ROOT), **kw)


def prepare(work: str, triangles: float, lights: int, budget: str, width: int, height: int) -> str:
    """The chunk store, generated (tinted glass grey) and subdivided unless
    already there."""
    soup, grey, store = (os.path.join(work, n) for n in ("soup", "soup-grey", "store"))
    if not os.path.exists(os.path.join(store, "header.msgpack")) and not os.path.isdir(store):
        os.makedirs(work, exist_ok=True)
        _dosppm("scenes", "generate", "building", "--triangles", str(int(triangles)), "--lights", str(lights),
                "--width", str(width), "--height", str(height), "--seed", "1", "--out", soup)
        grey_glass_soup(soup, grey)
        _dosppm("subdivide", grey, "--budget", budget, "--out", store)
    return store


def grey_glass(materials) -> None:
    """Tinted glass made grey, in place (pbrt-v4 has no tinted dielectric)."""
    for i, name in enumerate(materials.names):
        if name == "glass-tinted":
            materials.reflectance[i] = materials.reflectance[i].mean()


def grey_glass_soup(src: str, dst: str) -> None:
    soup = open_soup(src)
    grey_glass(soup.header.materials)
    writer = SoupWriter(dst)
    for _start, corners, material in soup.blocks():
        writer.append(corners, material)
    writer.close(soup.header)


def reference(args) -> np.ndarray | None:
    """pbrt-v4's converged image of the same building, or None without
    pbrt-v4 (then no relMSE is reported)."""
    if not args.reference_spp or pbrt.missing_reason():
        print(f"no reference: {pbrt.missing_reason() or '--reference-spp 0'}", file=sys.stderr)
        return None
    scene = building_scene(triangles=int(args.triangles), lights=args.lights, floors=2, seed=1,
                           width=args.width, height=args.height)
    grey_glass(scene.materials)
    key = (f"building-{int(args.triangles)}-{args.lights}-1-{args.width}x{args.height}-grey-"
           f"{args.reference_spp}spp")
    return pbrt_reference(scene, key, args.reference_spp, args.cache)


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _poll(port: int) -> dict | None:
    try:
        with urllib.request.urlopen(f"http://127.0.0.1:{port}/status", timeout=2) as r:
            return json.load(r)
    except (OSError, ValueError):
        return None


def run_dosppm(store: str, seconds: float, flags: list[str], out: str) -> dict:
    """One service render with its status timeline."""
    port = _free_port()
    cmd = [sys.executable, "-P", "-m", "services.cli", "render", store, "--tracers", "2", "--time", str(seconds),
           "--out", out, "--http", f"127.0.0.1:{port}", "--quiet", *flags]
    t0 = time.monotonic()
    proc = subprocess.Popen(cmd, cwd=ROOT, env=dict(os.environ, PYTHONPATH=ROOT))
    timeline, tracers = [], []
    while proc.poll() is None:
        st = _poll(port)
        if st and st.get("seconds"):
            tracers = st.get("tracers") or tracers
            point = {k: st.get(k) for k in ("seconds", "photons_emitted", "photons_committed", "hit_points",
                                            "iteration", "eye_iterations_in_flight")}
            point["photons_completed"] = st.get("counters", {}).get("photons_completed")
            point["latency_s"] = st.get("photon_job_latency_s")
            timeline.append(point)
        time.sleep(0.5)
    wall = time.monotonic() - t0
    if proc.returncode:
        raise RuntimeError(f"{' '.join(cmd)} exited with {proc.returncode}")
    with open(os.path.splitext(out)[0] + ".json", encoding="utf-8") as f:
        summary = json.load(f)
    half = next((p for p in timeline if p["seconds"] >= seconds / 2), None)
    render_s = summary.get("render_seconds") or summary.get("seconds") or seconds
    return {"photons": summary["counters"]["photons_emitted"], "photons_applied": summary["photons_applied"],
            "eye_iterations": summary["iteration"], "hit_points": summary["counters"]["hit_points"],
            "render_s": render_s, "wall_s": round(wall, 1),
            "hit_points_per_s": summary["counters"]["hit_points"] / render_s,
            "photons_per_s": summary["counters"]["photons_emitted"] / render_s,
            "committed_at_half": (half["photons_committed"] / half["photons_emitted"]
                                  if half and half["photons_emitted"] else None),
            "half": half, "timeline": timeline[::4], "tracers": [_time_split(t) for t in tracers]}


def _time_split(t: dict) -> dict:
    """A tracer's seconds by what it did, from its last heartbeat: tracing
    (busy less waiting for chunk loads), waiting for loads, idle, and its
    message handling."""
    keys = ("busy_s", "load_wait_s", "load_s", "idle_s", "receive_s", "step_send_s", "cpu_s", "chunk_loads",
            "steps", "rays_traced", "photons_traced")
    out = {k: t.get(k) for k in keys}
    if t.get("busy_s") is not None and t.get("load_wait_s") is not None:
        out["tracing_s"] = round(t["busy_s"] - t["load_wait_s"], 3)
    return out


def run_osppm(store: str, seconds: float, flags: list[str], out: str) -> dict:
    log = os.path.splitext(out)[0] + ".log.jsonl"
    if os.path.exists(log):
        os.remove(log)
    t0 = time.monotonic()
    _dosppm("render", store, "--mode", "osppm", "--time", str(seconds), "--out", out, "--log", log, "--quiet",
            *flags)
    with open(log, encoding="utf-8") as f:
        last = [json.loads(line) for line in f if line.strip()][-1]
    render_s = last.get("seconds") or seconds
    return {"photons": last["photons"], "hit_points": last["hit_points"], "render_s": render_s,
            "wall_s": round(time.monotonic() - t0, 1), "hit_points_per_s": last["hit_points"] / render_s,
            "photons_per_s": last["photons"] / render_s, "iterations": last.get("iteration")}


def run(args) -> dict:
    store = prepare(args.work, args.triangles, args.lights, args.budget, args.width, args.height)
    cost = sorted(ChunkStore.open(store).chunk_memory.tolist())
    two_chunks = int(cost[-1] + cost[-2])
    extra = args.extra.split() if args.extra else []
    runs = {"dosppm out of core": (run_dosppm, ["--memory", args.memory, *extra]),
            "dosppm resident": (run_dosppm, extra),
            "osppm out of core": (run_osppm, ["--memory", str(two_chunks)]),
            "osppm resident": (run_osppm, ["--memory", str(int(sum(cost)) + (256 << 20))])}
    if args.only:
        runs = {name: runs[name] for name in args.only}
    ref = reference(args)
    rows = {name: [] for name in runs}
    for rep in range(args.repeats):
        for name, (fn, flags) in runs.items():     # interleaved: the machine's drift falls on all alike
            out = os.path.join(args.work, "out", f"{name.replace(' ', '-')}.exr")
            r = fn(store, args.seconds, flags, out)
            if ref is not None:
                r |= score(read_exr(out)[0], ref)
            print(f"{name}: {r['photons']:,} photons, {r['hit_points']:,} hit points, "
                  f"{r['hit_points_per_s']:,.0f} hit points/s, relMSE {r.get('relmse')}", file=sys.stderr)
            rows[name].append(r)
    keys = ("photons_per_s", "hit_points_per_s") + (("relmse", "bias") if ref is not None else ())
    med = {name: {k: statistics.median([r[k] for r in rs]) for k in keys} for name, rs in rows.items()}
    return {"scene": f"generated building, {int(args.triangles):,} triangles, {args.lights} lights, "
                     f"{args.width}x{args.height}, tinted glass grey, {len(cost)} chunks ({args.budget} budget)",
            "reference": f"pbrt-v4 path, {args.reference_spp} spp" if ref is not None else None,
            "seconds": args.seconds, "memory": args.memory, "osppm_memory_bytes": two_chunks,
            "repeats": args.repeats, "runs": rows, "medians": med}


def _latency_at_half(run: dict) -> float | None:
    """The median photon job latency the status page showed half-way."""
    half = run.get("half") or {}
    lat = half.get("latency_s") or {}
    return lat.get("median")


def report(res: dict) -> str:
    scored = all("relmse" in m for m in res["medians"].values())
    lines = [f"{res['scene']}, {res['seconds']:g} s a render, medians of {res['repeats']}; DOSPPM with 2 "
             f"tracers, out of core at --memory {res['memory']} each; OSPPM out of core with room for two "
             "chunks." + (f" relMSE against {res['reference']}." if scored else ""), "",
             "| run | photons/s | hit points/s | eye iterations | photons committed half-way | "
             "job latency, median (s) | tracers tracing / loading |" + (" relMSE | mean bias |" if scored else ""),
             "|---|---|---|---|---|---|---|" + ("---|---|" if scored else "")]
    for name, rs in res["runs"].items():
        m = res["medians"][name]
        eye = statistics.median([r["eye_iterations"] for r in rs]) if "eye_iterations" in rs[0] else "-"
        half = [r["committed_at_half"] for r in rs if r.get("committed_at_half") is not None]
        lat = [_latency_at_half(r) for r in rs if _latency_at_half(r) is not None]
        lines.append(f"| {name} | {m['photons_per_s']:,.0f} | {m['hit_points_per_s']:,.0f} | {eye} | "
                     f"{f'{statistics.median(half):.0%}' if half else '-'} | "
                     f"{f'{statistics.median(lat):.1f}' if lat else '-'} | {_shares(rs)} |"
                     + (f" {m['relmse']:.4g} | {m['bias']:+.2%} |" if scored else ""))
    ratio = []
    for mode in [m for m in ("dosppm", "osppm") if f"{m} resident" in res["medians"]
                 and f"{m} out of core" in res["medians"]]:
        a, b = res["medians"][f"{mode} out of core"], res["medians"][f"{mode} resident"]
        ratio.append(f"{mode}: hit points/s out of core {a['hit_points_per_s'] / b['hit_points_per_s']:.2f}x "
                     f"the resident run's, photons/s {a['photons_per_s'] / b['photons_per_s']:.2f}x"
                     + (f", relMSE {a['relmse'] / b['relmse']:.2f}x" if scored else ""))
    return "\n".join(lines + ["", "; ".join(ratio) + "."])


def _shares(rs: list[dict]) -> str:
    """The tracers' median share of the render tracing and waiting for
    chunk loads (from their last heartbeat; '-' for OSPPM)."""
    per_run = [(sum(t["tracing_s"] for t in r["tracers"]), sum(t["load_wait_s"] for t in r["tracers"]),
                len(r["tracers"]) * r["render_s"]) for r in rs if r.get("tracers")]
    if not per_run:
        return "-"
    tracing = statistics.median(a / c for a, _, c in per_run)
    loading = statistics.median(b / c for _, b, c in per_run)
    return f"{tracing:.0%} / {loading:.0%}"


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--seconds", type=float, default=30.0)
    p.add_argument("--repeats", type=int, default=1)
    p.add_argument("--triangles", type=float, default=5e6)
    p.add_argument("--lights", type=int, default=200)
    p.add_argument("--budget", default="128MiB")
    p.add_argument("--memory", default="100MiB")
    p.add_argument("--width", type=int, default=256)
    p.add_argument("--height", type=int, default=256)
    p.add_argument("--work", default=WORK)
    p.add_argument("--only", nargs="*", help="run only these (names as in the table)")
    p.add_argument("--reference-spp", type=int, default=4096, help="pbrt-v4's samples a pixel (0: no relMSE)")
    p.add_argument("--cache", default="~/.cache/dosppm/references")
    p.add_argument("--extra", default="", help="more flags for the DOSPPM runs, e.g. '--min-photon-jobs 64'")
    p.add_argument("--json", default=os.path.join(ROOT, "benchmarks", "results", "out-of-core-eye.json"))
    args = p.parse_args(argv)
    res = run(args)
    print(report(res))
    write_results(args.json, res)
    return 0


if __name__ == "__main__":
    sys.exit(main())
