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
count once its last path has ended).

    python benchmarks/out_of_core_eye.py [--seconds 30] [--repeats 1]

The scene is generated once into --work (about 2 minutes, 1.5 GB).
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

from dosppm_core.chunks.store import ChunkStore  # noqa: E402
from services.evaluation.provenance import write_results  # noqa: E402

WORK = os.path.join(os.path.expanduser("~"), ".cache", "dosppm", "bench", "building-5M")


def _dosppm(*args: str, **kw) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-P", "-m", "services.cli", *args], cwd=ROOT, check=True,
                          env=dict(os.environ, PYTHONPATH=ROOT), **kw)


def prepare(work: str, triangles: float, lights: int, budget: str, width: int, height: int) -> str:
    """The chunk store, generated and subdivided unless already there."""
    soup, store = os.path.join(work, "soup"), os.path.join(work, "store")
    if not os.path.exists(os.path.join(store, "header.msgpack")) and not os.path.isdir(store):
        os.makedirs(work, exist_ok=True)
        _dosppm("scenes", "generate", "building", "--triangles", str(int(triangles)), "--lights", str(lights),
                "--width", str(width), "--height", str(height), "--seed", "1", "--out", soup)
        _dosppm("subdivide", soup, "--budget", budget, "--out", store)
    return store


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
    timeline = []
    while proc.poll() is None:
        st = _poll(port)
        if st and st.get("seconds"):
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
            "half": half, "timeline": timeline[::4]}


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
    rows = {name: [] for name in runs}
    for rep in range(args.repeats):
        for name, (fn, flags) in runs.items():     # interleaved: the machine's drift falls on all alike
            r = fn(store, args.seconds, flags, os.path.join(args.work, "out", f"{name.replace(' ', '-')}.exr"))
            print(f"{name}: {r['photons']:,} photons, {r['hit_points']:,} hit points, "
                  f"{r['hit_points_per_s']:,.0f} hit points/s", file=sys.stderr)
            rows[name].append(r)
    med = {name: {k: statistics.median([r[k] for r in rs]) for k in ("photons_per_s", "hit_points_per_s")}
           for name, rs in rows.items()}
    return {"scene": f"generated building, {int(args.triangles):,} triangles, {args.lights} lights, "
                     f"{args.width}x{args.height}, {len(cost)} chunks ({args.budget} budget)",
            "seconds": args.seconds, "memory": args.memory, "osppm_memory_bytes": two_chunks,
            "repeats": args.repeats, "runs": rows, "medians": med}


def _latency_at_half(run: dict) -> float | None:
    """The median photon job latency the status page showed half-way."""
    half = run.get("half") or {}
    lat = half.get("latency_s") or {}
    return lat.get("median")


def report(res: dict) -> str:
    lines = [f"{res['scene']}, {res['seconds']:g} s a render, medians of {res['repeats']}; DOSPPM with 2 "
             f"tracers, out of core at --memory {res['memory']} each; OSPPM out of core with room for two "
             "chunks.", "",
             "| run | photons/s | hit points/s | eye iterations | photons committed half-way | "
             "job latency, median (s) |",
             "|---|---|---|---|---|---|"]
    for name, rs in res["runs"].items():
        m = res["medians"][name]
        eye = statistics.median([r["eye_iterations"] for r in rs]) if "eye_iterations" in rs[0] else "-"
        half = [r["committed_at_half"] for r in rs if r.get("committed_at_half") is not None]
        lat = [_latency_at_half(r) for r in rs if _latency_at_half(r) is not None]
        lines.append(f"| {name} | {m['photons_per_s']:,.0f} | {m['hit_points_per_s']:,.0f} | {eye} | "
                     f"{f'{statistics.median(half):.0%}' if half else '-'} | "
                     f"{f'{statistics.median(lat):.1f}' if lat else '-'} |")
    ratio = []
    for mode in [m for m in ("dosppm", "osppm") if f"{m} resident" in res["medians"]
                 and f"{m} out of core" in res["medians"]]:
        a, b = res["medians"][f"{mode} out of core"], res["medians"][f"{mode} resident"]
        ratio.append(f"{mode}: hit points/s out of core {a['hit_points_per_s'] / b['hit_points_per_s']:.2f}x "
                     f"the resident run's, photons/s {a['photons_per_s'] / b['photons_per_s']:.2f}x")
    return "\n".join(lines + ["", "; ".join(ratio) + "."])


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
    p.add_argument("--extra", default="", help="more flags for the DOSPPM runs, e.g. '--min-photon-jobs 64'")
    p.add_argument("--json", default=os.path.join(ROOT, "benchmarks", "results", "out-of-core-eye.json"))
    args = p.parse_args(argv)
    res = run(args)
    print(report(res))
    write_results(args.json, res)
    return 0


if __name__ == "__main__":
    sys.exit(main())
