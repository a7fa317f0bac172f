"""Issue 17, parts 3 and 4: work chosen by the renderer to hide chunk loads.

On a generated building (5M triangles, 8 chunks of about 85 MiB) with
memory for two chunks (`--memory 200MiB`), in one run on one machine:

- OSPPM with the photons per iteration it chooses itself, beside every
  hand-tuned setting in `--ppi`: the target is the default at 90% or more
  of the best hand-tuned one. Peak RSS of each run beside it.
- DOSPPM (a server and two tracers, each holding half the chunks, two of
  them resident) at 8 and 16 chunks: photons/s, and each tracer's time
  busy, waiting for chunk loads, and idle; against OSPPM with every chunk
  resident. DOSPPM at its defaults too (no --memory: every chunk resident
  on this machine), at 8 and 16 chunks. The targets: tracers busy 85% of the render, and
  photons/s within 10% of OSPPM with every chunk resident.

photons/s is photons applied over the render's seconds, the drain of the
queues at the end included. Medians of `--repeats` runs, every sample kept;
the settings run in rounds, one run of each per round, after a warm-up.

    python benchmarks/pacing.py --seconds 30 --repeats 3 --json benchmarks/results/pacing.json
"""
from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, ROOT)

from harness.provenance import median_of, write_results  # noqa: E402

MiB = 1 << 20


def _dosppm(args: list[str], timeout_s: float) -> tuple[float, float]:
    """Run `dosppm ARGS`: (peak RSS in bytes, wall seconds). The peak is
    wait4's high-water mark: the largest of the command and its children
    (local tracers), interpreter and kernels included."""
    env = dict(os.environ, PYTHONPATH=ROOT + os.pathsep + os.environ.get("PYTHONPATH", ""))
    t0 = time.monotonic()
    with tempfile.TemporaryFile("w+") as err:
        p = subprocess.Popen([sys.executable, "-m", "services.cli", *args], env=env,
                             stdout=subprocess.DEVNULL, stderr=err, text=True)
        while time.monotonic() - t0 < timeout_s:
            pid, status, usage = os.wait4(p.pid, os.WNOHANG)
            if pid:
                p.returncode = os.waitstatus_to_exitcode(status)
                break
            time.sleep(0.2)
        else:
            p.kill()
            raise RuntimeError(f"dosppm {' '.join(args[:3])} did not finish in {timeout_s} s")
        if p.returncode:
            err.seek(0)
            raise RuntimeError(f"dosppm {' '.join(args[:3])} exited {p.returncode}: {err.read()[-1500:]}")
    return usage.ru_maxrss * 1024, time.monotonic() - t0


def _store(work: str, triangles: float, chunks: int | None) -> str:
    soup, store = os.path.join(work, "building"), os.path.join(work, f"building-{chunks or 'budget'}.chunks")
    if not os.path.exists(soup):
        _dosppm(["scenes", "generate", "building", "--triangles", str(int(triangles)), "--out", soup], 600)
    if not os.path.exists(store):
        split = ["--chunks", str(chunks)] if chunks else ["--budget", "128MiB"]
        _dosppm(["subdivide", soup, *split, "--out", store], 1200)
    return store


def _osppm(store: str, seconds: float, memory: str | None, ppi: int | None, work: str) -> dict:
    out, log = os.path.join(work, "osppm.exr"), os.path.join(work, "osppm.log")
    if os.path.exists(log):
        os.remove(log)
    args = ["render", store, "--mode", "osppm", "--time", str(seconds), "--out", out, "--log", log, "--quiet"]
    args += ["--memory", memory] if memory else []
    args += ["--photons-per-iteration", str(ppi)] if ppi else []
    rss, wall = _dosppm(args, 10 * seconds + 300)
    with open(log, encoding="utf-8") as f:
        last = json.loads(f.read().splitlines()[-1])
    return {"photons_per_s": last["photons"] / last["seconds"], "photons": last["photons"],
            "iterations": last["iteration"], "seconds": last["seconds"], "peak_rss_mib": rss / MiB,
            "wall_s": wall}


def _dosppm_render(store: str, seconds: float, memory: str | None, work: str) -> dict:
    out = os.path.join(work, "dosppm.exr")
    args = ["render", store, "--time", str(seconds), "--out", out, "--quiet"]
    args += ["--memory", memory] if memory else []
    rss, wall = _dosppm(args, 10 * seconds + 300)
    with open(os.path.join(work, "dosppm.json"), encoding="utf-8") as f:
        doc = json.load(f)
    secs = doc["seconds"]
    tracers = [{k: t.get(k) for k in ("id", "chunks", "busy_s", "idle_s", "chunk_loads", "load_s", "load_wait_s",
                                      "wasted_prefetches", "queue_target", "rays_traced")} for t in doc["tracers"]]
    busy = [t["busy_s"] / secs for t in tracers]
    tracing = [(t["busy_s"] - t["load_wait_s"]) / secs for t in tracers]
    return {"photons_per_s": doc["photons_applied"] / secs, "hit_points_per_s": doc["hit_points_per_s"],
            "photons_per_eye_iteration": doc["photons_applied"] / max(doc["iteration"], 1), "seconds": secs, "wall_s": wall, "busy_share": min(busy), "tracing_share": min(tracing),
            "chunk_loads": sum(t["chunk_loads"] for t in tracers), "peak_rss_mib": rss / MiB,
            "tracers": tracers}


def _interleaved(runs: dict, repeats: int) -> dict:
    """Each of `runs` (name: zero-argument function) `repeats` times, in
    rounds of one run each, so that drift on a shared machine (the page
    cache after a store is written, another tenant) falls on every setting
    alike rather than on whichever ran first; the median of each, every
    sample kept."""
    samples = {name: [] for name in runs}
    for _ in range(repeats):
        for name, fn in runs.items():
            samples[name].append(fn())
    return {name: median_of(got) for name, got in samples.items()}


def run(args) -> dict:
    os.makedirs(args.work, exist_ok=True)
    store = _store(args.work, args.triangles, None)
    stores = {c: store if c == 8 else _store(args.work, args.triangles, c) for c in args.chunks}
    s, r, m = args.seconds, args.repeats, args.memory
    _osppm(store, min(s, 5), m, None, args.work)    # warm-up, not counted: kernels cached, store read
    runs = {"osppm auto": lambda: _osppm(store, s, m, None, args.work)}
    runs.update({f"osppm {ppi}": (lambda ppi=ppi: _osppm(store, s, m, ppi, args.work)) for ppi in args.ppi})
    # OSPPM's --memory defaults to two chunk budgets: every chunk resident takes a limit above the store.
    runs["osppm resident"] = lambda: _osppm(store, s, "64GiB", None, args.work)
    runs.update({f"dosppm {c}": (lambda st=st: _dosppm_render(st, s, m, args.work)) for c, st in stores.items()})
    # No --memory: each tracer's share of the machine (24 GiB here) holds every chunk.
    runs.update({f"dosppm {c} resident": (lambda st=st: _dosppm_render(st, s, None, args.work))
                 for c, st in stores.items()})
    got = _interleaved(runs, r)
    osppm = {"auto": got["osppm auto"], **{str(ppi): got[f"osppm {ppi}"] for ppi in args.ppi}}
    best = max((k for k in osppm if k != "auto"), key=lambda k: osppm[k]["photons_per_s"])
    resident = got["osppm resident"]
    dosppm = {str(c): got[f"dosppm {c}"] for c in stores}
    dosppm.update({f"{c} resident": got[f"dosppm {c} resident"] for c in stores})
    # Equal work: OSPPM, every chunk resident, on the same store, with as
    # many photons per eye iteration as each DOSPPM row made (its eye
    # iterations run beside the photons: far fewer than OSPPM's default 1.5
    # a pixel out of core, more with every chunk resident).
    equal = _interleaved({c: (lambda c=c: _osppm(stores[int(c.split()[0])], s, "64GiB",
                                                 int(dosppm[c]["photons_per_eye_iteration"]), args.work))
                          for c in dosppm}, r)
    auto = osppm["auto"]["photons_per_s"]
    return {"triangles": args.triangles, "memory": m, "seconds": s, "osppm": osppm, "osppm_resident": resident,
            "osppm_resident_equal_work": equal, "dosppm": dosppm, "best_hand_tuned": best,
            "long": _long_renders(store, args) if args.long_seconds > 0 else None,
            "auto_over_best": auto / osppm[best]["photons_per_s"],
            "dosppm_over_osppm_resident": {c: d["photons_per_s"] / resident["photons_per_s"]
                                           for c, d in dosppm.items()},
            "dosppm_over_osppm_resident_equal_work": {c: d["photons_per_s"] / equal[c]["photons_per_s"]
                                                      for c, d in dosppm.items()}}


def _long_renders(store: str, args) -> dict:
    """DOSPPM at 8 chunks beside OSPPM with every chunk resident at the
    same photons per eye iteration, for `--long-seconds`, in pairs: the
    queues' ramp at the start and their drain at the end (every chunk
    loaded again for fewer and fewer rays) are a fixed cost, a sixth of
    a 30 s render, that a long render spreads thin. Ratio per pair; medians."""
    s, pairs = args.long_seconds, []
    for _ in range(args.long_repeats):
        d = _dosppm_render(store, s, args.memory, args.work)
        o = _osppm(store, s, "64GiB", int(d["photons_per_eye_iteration"]), args.work)
        pairs.append({"dosppm": d, "osppm_resident_equal_work": o,
                      "ratio": d["photons_per_s"] / o["photons_per_s"]})
    return {"seconds": s, "pairs": pairs, "ratio_median": statistics.median(p["ratio"] for p in pairs)}


def _waiting(d: dict) -> float:
    """The larger of the two tracers' share of the render spent waiting:
    idle (for portal packages, the server's credit, eye tiles) or for a
    chunk load. What is neither is tracing or handling messages. Median
    over the runs."""
    def most(s):
        return max((t["idle_s"] + t["load_wait_s"]) / s["seconds"] for t in s["tracers"])
    return statistics.median(most(s) for s in d.get("samples", [d]))


def report(doc: dict) -> str:
    """The Markdown tables docs/out-of-core.md quotes (benchmarks/tables.py)."""
    def k(x):
        return f"{x / 1e3:,.0f}k"
    lines = ["| OSPPM, photons per iteration | photons/s | mean per iteration | peak RSS |", "|---|---|---|---|"]
    rows = [("chosen by the renderer (default)", doc["osppm"]["auto"])]
    rows += [(f"{int(p):,} (hand-tuned)", d) for p, d in doc["osppm"].items() if p != "auto"]
    rows += [("every chunk resident, default", doc["osppm_resident"])]
    equal_work = doc["osppm_resident_equal_work"]
    if "photons_per_s" in equal_work:      # files before each DOSPPM row had its own
        equal_work = {"8": equal_work}
    rows += [(f"every chunk resident, DOSPPM's ({c} chunks) per eye iteration", d) for c, d in equal_work.items()]
    for name, d in rows:
        lines.append(f"| {name} | {k(d['photons_per_s'])} | {k(d['photons'] / d['iterations'])} "
                     f"| {d['peak_rss_mib']:,.0f} MiB |")
    lines += ["", f"The default reaches {doc['auto_over_best']:.0%} of the best hand-tuned setting "
              f"({int(doc['best_hand_tuned']):,}).", "",
              "| DOSPPM, 2 tracers | photons/s | of OSPPM, all resident | at equal work | tracers busy "
              "| tracing | waiting | chunk loads | peak RSS, largest process |",
              "|---|---|---|---|---|---|---|---|---|"]
    equal = doc.get("dosppm_over_osppm_resident_equal_work", {})
    for c, d in doc["dosppm"].items():
        name = f"{c} chunks, {doc['memory']} each" if "resident" not in c else f"{c.split()[0]} chunks, all resident"
        eq = f"{equal[c]:.2f}" if c in equal else "–"
        lines.append(f"| {name} | {k(d['photons_per_s'])} | {doc['dosppm_over_osppm_resident'][c]:.2f} | {eq} "
                     f"| {d['busy_share']:.0%} | {d['tracing_share']:.0%} | {_waiting(d):.0%} | {d['chunk_loads']:.0f} "
                     f"| {d['peak_rss_mib']:,.0f} MiB |")
    long = doc.get("long")
    if long:
        lines += ["", f"| {long['seconds']:.0f} s renders, in pairs | DOSPPM, 8 chunks | OSPPM, all resident, "
                  "equal work | ratio |", "|---|---|---|---|"]
        for i, p in enumerate(long["pairs"], 1):
            lines.append(f"| pair {i} | {k(p['dosppm']['photons_per_s'])} "
                         f"| {k(p['osppm_resident_equal_work']['photons_per_s'])} | {p['ratio']:.2f} |")
        lines.append(f"| median | | | {long['ratio_median']:.2f} |")
    return "\n".join(lines) + "\n"


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--triangles", type=float, default=5e6)
    p.add_argument("--memory", default="200MiB", help="per process: two chunks of the 8")
    p.add_argument("--seconds", type=float, default=30)
    p.add_argument("--repeats", type=int, default=3)
    p.add_argument("--ppi", type=int, nargs="+", default=[250_000, 500_000, 1_000_000, 2_000_000, 4_000_000])
    p.add_argument("--chunks", type=int, nargs="+", default=[8, 16])
    p.add_argument("--long-seconds", type=float, default=120,
                   help="also DOSPPM beside OSPPM resident at equal work this long, in pairs (0: not)")
    p.add_argument("--long-repeats", type=int, default=2)
    p.add_argument("--work", default="/tmp/dosppm-pacing")
    p.add_argument("--json", default=os.path.join(ROOT, "benchmarks", "results", "pacing.json"))
    args = p.parse_args()
    doc = run(args)
    write_results(args.json, doc)
    print(report(doc))
    print(f"OSPPM auto {doc['osppm']['auto']['photons_per_s'] / 1e3:.0f}k photons/s = "
          f"{doc['auto_over_best']:.2f} of the best hand-tuned ({doc['best_hand_tuned']})")
    for c, d in doc["dosppm"].items():
        print(f"DOSPPM c={c}: {d['photons_per_s'] / 1e3:.0f}k photons/s "
              f"({doc['dosppm_over_osppm_resident'][c]:.2f} of OSPPM resident, "
              f"{doc.get('dosppm_over_osppm_resident_equal_work', {}).get(c, float('nan')):.2f} at equal work), "
              f"busy {d['busy_share']:.0%}, tracing {d['tracing_share']:.0%}")


if __name__ == "__main__":
    main()
