"""Out of core end to end (issue 17, part 2): a generated building whose
chunk store is at least twice a per-process memory limit is generated,
subdivided, and rendered in OSPPM and in DOSPPM (a server and two
tracers), and every process's peak resident memory is set against the
limit. The peak is each child's `ru_maxrss` from wait4 (the kernel's
high-water mark, interpreter and kernels included).

    python benchmarks/out_of_core_pipeline.py --triangles 34e6 --limit 400MiB \\
        --json benchmarks/results/out-of-core-pipeline.json

The target is every process under the limit; the file records which are
not. About 10 minutes on 2 cores, and 2.5 GB of disk in --work.

With no tuning: `--memory default --queue-memory default --cgroup` leaves
the rendering processes' memory flags out and runs each step in its own
memory cgroup of `--limit` (root only): the limit is enforced, a step past
it is killed, and the processes choose their chunk and queue memory from
it as in a container.
"""
from __future__ import annotations

import argparse
import os
import re
import shutil
import socket
import subprocess
import sys
import time

import numpy as np

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, ROOT)
MiB = 1 << 20


class MemoryCgroups:
    """One memory cgroup per step, each limited to `limit` bytes (cgroup v1
    memory.limit_in_bytes or v2 memory.max; this machine has no swap, so
    a step past it is killed): the limit enforced, not only measured, and
    seen by dosppm's defaults (`pacing.machine_memory_bytes`) as a
    container's would be. `procs_file(name)` is None where this process
    may not make cgroups (not root, no memory controller)."""

    KNOBS = (("/sys/fs/cgroup/memory", "memory.limit_in_bytes", "memory.max_usage_in_bytes"),
             ("/sys/fs/cgroup", "memory.max", "memory.peak"))

    def __init__(self, limit: int):
        self.limit, self.made = limit, {}

    def procs_file(self, name: str) -> str | None:
        for base, knob, peak in self.KNOBS:
            path = os.path.join(base, f"dosppm-{os.getpid()}-{name.replace(' ', '-')}")
            try:
                os.makedirs(path, exist_ok=True)
                with open(os.path.join(path, knob), "w", encoding="utf-8") as f:
                    f.write(str(self.limit))
            except OSError:
                try:
                    os.rmdir(path)
                except OSError:
                    pass
                continue
            self.made[name] = (path, peak)
            return os.path.join(path, "cgroup.procs")
        return None

    def peak(self, name: str) -> int | None:
        """The cgroup's own high-water mark. It counts the page cache of
        the files the step reads and writes (reclaimed at the limit, so a
        step writing a store reaches it) and not the shared libraries
        another group touched first: a record, not the process's peak."""
        path, peak = self.made[name]
        try:
            with open(os.path.join(path, peak), encoding="utf-8") as f:
                return int(f.read().strip())
        except (OSError, ValueError):
            return None

    def close(self) -> None:
        for path, _peak in self.made.values():
            try:
                os.rmdir(path)
            except OSError:
                pass


def _dosppm(*args: str, cgroup: str | None = None) -> subprocess.Popen:
    """`dosppm ARGS` in a child; in the cgroup whose procs file is
    `cgroup`, joined before exec, so every byte it maps is counted."""
    env = dict(os.environ, PYTHONPATH=ROOT + os.pathsep + os.environ.get("PYTHONPATH", ""))

    def join():
        with open(cgroup, "w", encoding="utf-8") as f:
            f.write(str(os.getpid()))
    return subprocess.Popen([sys.executable, "-m", "services.cli", *args], stdout=subprocess.DEVNULL,
                            stderr=subprocess.PIPE, text=True, env=env, preexec_fn=join if cgroup else None)


def _peak(p: subprocess.Popen, timeout_s: float) -> tuple[int, float, str]:
    """Wait for `p` (its exit status checked): (peak RSS bytes, seconds,
    the end of what it wrote to stderr)."""
    t0 = time.monotonic()
    while time.monotonic() - t0 < timeout_s:
        pid, status, usage = os.wait4(p.pid, os.WNOHANG)
        if pid:
            code = os.waitstatus_to_exitcode(status)
            if code != 0:
                raise RuntimeError(f"{p.args[3:5]} exited {code}: {p.stderr.read()[-2000:]}")
            return usage.ru_maxrss * 1024, time.monotonic() - t0, p.stderr.read()[-4000:]
        time.sleep(0.2)
    p.kill()
    raise RuntimeError(f"{p.args[3:5]} did not finish in {timeout_s} s")


def _own_rss() -> int:
    """This process's RSS now, which a child forked now starts from (its own
    ru_maxrss may be its parent's, carried across exec)."""
    with open("/proc/self/status", encoding="utf-8") as f:
        return next(int(line.split()[1]) * 1024 for line in f if line.startswith("VmRSS"))


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _mean_luminance(path: str) -> float:
    from dosppm_core.film import read_exr
    img = read_exr(path)[0]
    return float((img @ np.array([0.2126, 0.7152, 0.0722])).mean()) if np.isfinite(img).all() else float("nan")


def _flags(memory: str, queue_memory: str) -> list[str]:
    """--memory and --queue-memory for a rendering process; 'default'
    leaves a flag out, so the process chooses (from its cgroup's limit)."""
    return [x for flag, v in (("--memory", memory), ("--queue-memory", queue_memory)) if v != "default"
            for x in (flag, v)]


def _wrote(stderr: str) -> dict:
    """The render's own last line, "wrote OUT after K iterations, N photons,
    S s": the photons in its image and its render clock."""
    m = re.findall(r"wrote \S+ after (\d+) iterations?, ([\d,]+) photons, ([\d.]+) s", stderr)
    if not m:
        return {}
    k, n, s = m[-1]
    return {"iterations": int(k), "photons_applied": int(n.replace(",", "")), "render_clock_s": float(s)}


def run(work: str, triangles: int, seconds: float, memory: str, queue_memory: str,
        cgroups: MemoryCgroups | None = None, photons: int | None = None) -> dict:
    """With `photons`, both renders stop once that many are emitted and
    drain (the same work in each); otherwise each has `seconds` as its
    deadline (--time)."""
    soup, store = os.path.join(work, "building"), os.path.join(work, "building.chunks")
    shutil.rmtree(work, ignore_errors=True)

    def step(name: str, *args: str) -> subprocess.Popen:
        cgroup = cgroups.procs_file(name) if cgroups else None
        if cgroups and cgroup is None:
            raise RuntimeError("--cgroup: cannot make a memory cgroup here (needs root and a memory controller)")
        return _dosppm(*args, cgroup=cgroup)
    # Every step in a child process: a child's ru_maxrss starts from its
    # parent's RSS at the fork, so this process must stay small.
    procs = {"generate": _peak(step("generate", "scenes", "generate", "building", "--triangles", str(triangles),
                                    "--lights", "64", "--out", soup), 1200)}
    procs["subdivide"] = _peak(step("subdivide", "subdivide", soup, "--budget", "64MiB", "--memory", "64MiB",
                                    "--grid", "262144", "--out", store), 1200)
    store_bytes = sum(os.path.getsize(os.path.join(store, f)) for f in os.listdir(store) if f.endswith(".bin"))
    shutil.rmtree(soup)
    flags = _flags(memory, queue_memory)
    stop = ["--photons", str(photons)] if photons else ["--time", str(seconds)]
    procs["osppm"] = _peak(step("osppm", "render", store, "--mode", "osppm", *stop, *flags,
                                "--out", os.path.join(work, "osppm.exr")), seconds + 600)
    port = _free_port()
    server = step("server", "server", store, "--bind", f"tcp://127.0.0.1:{port}", "--http", "off",
                  "--min-tracers", "2", *stop, "--threads", "1", *_flags("default", queue_memory),
                  "--out", os.path.join(work, "dosppm.exr"))
    tracers = [step(f"tracer {i}", "worker", "--server", f"tcp://127.0.0.1:{port}", "--store", store, *flags,
                    "--threads", "1", "--id", f"t{i}", "--cache-dir", os.path.join(work, f"cache{i}"))
               for i in range(2)]
    procs["server"] = _peak(server, seconds + 600)
    for i, t in enumerate(tracers):
        procs[f"tracer {i}"] = _peak(t, 120)
    from dosppm_core.chunks.store import ChunkStore      # after the children: this process stays small for them
    chunk_memory = ChunkStore.open(store).chunk_memory
    return {"store_bytes": store_bytes, "triangles": triangles, "render_s": None if photons else seconds,
            "photons": photons, "chunk_memory": memory,
            "queue_memory": queue_memory, "parent_rss_bytes": _own_rss(), "chunks": len(chunk_memory),
            "chunk_memory_bytes": float(sum(chunk_memory)),
            "processes": {k: {"peak_bytes": v[0], "seconds": round(v[1], 1),
                              **({"cgroup_peak_bytes": cgroups.peak(k)} if cgroups else {})}
                          for k, v in procs.items()},
            "renders": {m: _wrote(procs[k][2]) for m, k in (("osppm", "osppm"), ("dosppm", "server"))},
            "mean_luminance": {m: _mean_luminance(os.path.join(work, f"{m}.exr")) for m in ("osppm", "dosppm")}}


def report(doc: dict) -> str:
    """The table docs/out-of-core.md quotes (benchmarks/tables.py)."""
    limit, enforced = doc["limit_bytes"], doc.get("limit_enforced", False)
    if doc["chunk_memory"] == "default" and doc.get("queue_memory") == "default":
        holds = "no memory flags: the rendering processes chose their chunk and queue memory"
    else:
        holds = f"rendering processes hold {doc['chunk_memory']} of chunks and {doc.get('queue_memory', '?')} " \
                "of queued rays"
    lines = [f"{doc['triangles'] / 1e6:g}M triangles in {doc['chunks']} chunks: the store is "
             f"{doc['store_bytes'] / MiB:,.0f} MiB on disk ({doc['store_over_limit']}x the limit) and "
             f"{doc['chunk_memory_bytes'] / MiB:,.0f} MiB loaded ({doc['chunk_memory_over_limit']}x); "
             f"limit {limit / MiB:,.0f} MiB a process" + (", each in a memory cgroup of it (enforced)" if enforced
                                                          else "") + f"; {holds}; {_stop(doc)}.",
             "", "| process | peak RSS | under the limit | seconds |", "|---|---|---|---|"]
    for k, v in doc["processes"].items():
        ok = "yes" if v["peak_bytes"] <= limit else "**no**"
        secs = "with the server" if k.startswith("tracer") else f"{v['seconds']:,.1f}"
        lines.append(f"| {k} | {v['peak_bytes'] / MiB:,.0f} MiB | {ok} | {secs} |")
    lum, renders = doc["mean_luminance"], doc.get("renders", {})
    lines += ["", f"Mean luminance: OSPPM {lum['osppm']:.4g}, DOSPPM {lum['dosppm']:.4g}."]
    for m, r in renders.items():
        if r:
            lines.append(f"{m.upper()}: {r['photons_applied']:,} photons in the image after {r['iterations']} eye "
                         f"iterations, render clock {r['render_clock_s']:.1f} s.")
    return "\n".join(lines) + "\n"


def _stop(doc: dict) -> str:
    if doc.get("photons"):
        return f"each render stops at {doc['photons']:,} photons emitted and drains"
    return f"{doc['render_s']:g} s renders (--time, a deadline)"


def main(argv=None) -> int:
    from services.config import parse_bytes
    from harness.provenance import write_results
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--triangles", type=float, default=34e6)
    p.add_argument("--limit", default="400MiB", help="the per-process memory limit the store is twice of")
    p.add_argument("--memory", default="128MiB", help="resident chunks per rendering process (--memory; "
                   "'default': the renderer's own choice)")
    p.add_argument("--queue-memory", default="64MiB",
                   help="queued rays per rendering process, deposits held by the server (--queue-memory)")
    p.add_argument("--seconds", type=float, default=25, help="each render's deadline (--time)")
    p.add_argument("--photons", type=float, default=None,
                   help="instead of --seconds: each render stops once N photons are emitted, and drains")
    p.add_argument("--cgroup", action="store_true",
                   help="run each step in a memory cgroup of --limit: enforced, and what the defaults see")
    p.add_argument("--work", default="/tmp/dosppm-out-of-core")
    p.add_argument("--json", default=None)
    args = p.parse_args(argv)
    limit = parse_bytes(args.limit, "--limit")
    cgroups = MemoryCgroups(limit) if args.cgroup else None
    try:
        doc = run(args.work, int(args.triangles), args.seconds, args.memory, args.queue_memory, cgroups,
                  int(args.photons) if args.photons else None)
    finally:
        if cgroups:
            cgroups.close()
    doc["limit_bytes"], doc["limit_enforced"] = limit, bool(cgroups)
    doc["over_limit"] = sorted(k for k, v in doc["processes"].items() if v["peak_bytes"] > limit)
    doc["store_over_limit"] = round(doc["store_bytes"] / limit, 2)
    doc["chunk_memory_over_limit"] = round(doc["chunk_memory_bytes"] / limit, 2)
    for k, v in doc["processes"].items():
        print(f"{k:10s} peak {v['peak_bytes'] / MiB:6.0f} MiB  {v['seconds']:6.1f} s")
    print(f"store {doc['store_bytes'] / MiB:,.0f} MiB = {doc['store_over_limit']}x the limit on disk, "
          f"{doc['chunk_memory_over_limit']}x loaded ({doc['chunks']} chunks); over the limit: "
          f"{doc['over_limit'] or 'none'}; mean luminance {doc['mean_luminance']}; renders {doc['renders']}")
    if args.json:
        write_results(args.json, doc)
    shutil.rmtree(args.work, ignore_errors=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
