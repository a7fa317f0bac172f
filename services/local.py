"""Starting the roles: `serve` (the server, optionally with tracer processes
on this machine: `dosppm render`'s default), `work` (one tracer) and
`warm_kernels` (compile the numba kernels once, before any clock runs)."""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
import warnings

from services.cli import render as core
from dosppm_core.modes.sppm import RenderSettings
from dosppm_core.scene.model import SceneError

RENDER_KEYS = ("time", "photons", "iterations", "out", "seed", "gather", "alpha", "radius", "max_depth",
               "photons_per_iteration", "photons_per_job", "photon_batch", "width", "height", "threads",
               "budget", "chunks", "store_cache", "exposure", "log")


def render_local(args) -> int:
    """`dosppm render` in its default mode: a server in this process and
    `--tracers` tracer processes (default: one per core)."""
    values = {k: getattr(args, k) for k in RENDER_KEYS}
    n = args.tracers or os.cpu_count() or 1
    if n < 1:
        return core._error("--tracers must be >= 1")
    values.update({o: getattr(args, o) for o in ("cull", "concurrent", "client_batching")})
    values.update(bind="tcp://127.0.0.1:*", http=args.http, min_tracers=n,
                  min_photon_jobs=args.min_photon_jobs, snapshot_interval=args.snapshot_interval,
                  drain_timeout=60.0, tracer_timeout=args.tracer_timeout, checkpoint=args.checkpoint,
                  checkpoint_interval=args.checkpoint_interval, resume=args.resume)
    return serve(args.scene, values, quiet=args.quiet, spawn_tracers=n)


def _settings(v: dict) -> RenderSettings:
    s = RenderSettings(seed=v["seed"], alpha=v["alpha"], radius=v["radius"], max_depth=v["max_depth"],
                       gather=v["gather"], photons_per_iteration=v["photons_per_iteration"],
                       photons_per_job=v["photons_per_job"], photon_batch=v["photon_batch"],
                       threads=v["threads"], tile_pixels=4096, cull=v["cull"])
    s.validate()
    return s


def _resumed_settings(settings: RenderSettings, doc: dict) -> RenderSettings:
    """The render settings saved in a checkpoint win over the flags: a
    resumed render goes on exactly as it began."""
    for k, value in doc["settings"].items():
        if hasattr(settings, k):
            setattr(settings, k, value)
    settings.validate()
    return settings


def _open_store(scene: str, v: dict):
    ns = argparse.Namespace(scene=scene, budget=v["budget"], chunks=v["chunks"], width=v["width"],
                            height=v["height"],
                            store_cache=v["store_cache"] or core._default_store_cache())
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        store = core.open_store(ns)
    for w in caught:
        print(f"dosppm: warning: {w.message}", file=sys.stderr)
    return store


def _http(text: str):
    if text in (None, "", "off"):
        return None
    host, _, port = text.rpartition(":")
    if not host or not port.isdigit():
        raise ValueError(f"--http: expected HOST:PORT or 'off', got {text!r}")
    return host, int(port)


def serve(scene: str, v: dict, quiet: bool = False, spawn_tracers: int = 0) -> int:
    from services.progress import ProgressReporter, kernels_cached

    from services.server.node import Limits, ServerProcess
    say = (lambda *a: None) if quiet else (lambda *a: print(*a, file=sys.stderr))
    from services.server import checkpoint
    try:
        settings = _settings(v)
        http = _http(v["http"])
        store = _open_store(scene, v)
        resume = checkpoint.read(v["resume"], store.key) if v["resume"] else None
        if resume is not None:
            settings = _resumed_settings(settings, resume)
    except (SceneError, ValueError, OSError) as e:
        return core._error(str(e))
    ckpt = v["checkpoint"] or v["resume"] or (os.path.splitext(v["out"])[0] + ".checkpoint" if v["out"] else None)
    if not kernels_cached():
        say("compiling kernels (first run on this machine; cached afterwards, about a minute)...")
        warm_kernels()
    limits = Limits(v["time"], v["photons"], v["iterations"])
    if limits.seconds is None and limits.photons is None and limits.iterations is None:
        limits.seconds = 30.0
    kind = ("photons", limits.photons) if limits.photons else (
        ("iterations", limits.iterations) if limits.iterations else ("seconds", limits.seconds))
    reporter = ProgressReporter(kind, v["log"], quiet=quiet)
    try:
        server = ServerProcess(store, settings, bind=v["bind"], http=http, out=v["out"], limits=limits,
                               snapshot_interval_s=v["snapshot_interval"],
                               min_photon_jobs=v["min_photon_jobs"], min_tracers=v["min_tracers"],
                               threads=v["threads"], exposure=v["exposure"],
                               drain_timeout_s=v["drain_timeout"], reporter=reporter,
                               concurrent=v["concurrent"], client_batching=v["client_batching"],
                               tracer_timeout_s=v["tracer_timeout"], checkpoint_dir=ckpt,
                               checkpoint_interval_s=v["checkpoint_interval"], resume=resume,
                               curve_secret=v.get("curve_secret"), curve_clients=v.get("curve_clients"))
    except Exception as e:   # zmq bind errors and the like: one line, not a traceback
        return core._error(f"cannot start the server: {e}")
    cam = store.header.camera
    say(f"scene {store.header.name}: {store.source_triangles:,} triangles in {store.chunk_count} "
        f"chunk(s), {len(store.header.lights.kind)} lights, {cam.width}x{cam.height}")
    say(f"server {server.endpoint}" + (f", status {server.status_url}" if server.status_url else ""))
    tracers = _spawn_tracers(spawn_tracers, server.endpoint, store.path, v["threads"])
    server.watch = lambda: _early_exit(tracers, server)
    try:
        summary = server.run()
    finally:
        reporter.close()
        _reap(tracers)
    _write_summary(v["out"], summary)
    p = server.progress()
    say(f"{'interrupted: ' if server.interrupted else ''}wrote {v['out']} after {p.iteration} "
        f"iterations, {summary['photons_committed']:,} photons, {p.seconds:.1f} s")
    if server.failure:
        return core._error(server.failure, 1)
    return 130 if server.interrupted else 0


def _write_summary(out: str, summary: dict) -> None:
    """OUT.json beside the image: the server's accounting of the run
    (photons emitted, completed and applied, path ends, per tracer)."""
    if not out:
        return
    with open(os.path.splitext(out)[0] + ".json", "w", encoding="utf-8") as f:
        json.dump(summary, f, indent=1, default=str)


def _spawn_tracers(n: int, endpoint: str, store_path: str, threads: int) -> list:
    per = max(1, threads // max(n, 1))
    cmd = [sys.executable, "-m", "services.cli", "worker", "--server", endpoint, "--store", store_path,
           "--threads", str(per), "--quiet"]
    root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    env = dict(os.environ, PYTHONPATH=os.pathsep.join(filter(None, [root, os.environ.get("PYTHONPATH")])))
    return [subprocess.Popen(cmd + ["--id", f"local-{i}"], env=env) for i in range(n)]


def _early_exit(tracers: list, server) -> str | None:
    """A tracer process that died before the render ended."""
    for p in tracers:
        code = p.poll()
        if code is not None and code != 0:
            return f"tracer process {p.pid} exited with status {code}"
    return None


def _reap(tracers: list, timeout_s: float = 10.0) -> None:
    deadline = time.monotonic() + timeout_s
    for p in tracers:
        try:
            p.wait(max(0.1, deadline - time.monotonic()))
        except subprocess.TimeoutExpired:
            p.kill()
            p.wait()


def work(v: dict, quiet: bool = False) -> int:
    from services.cli.chunks import parse_bytes

    from services.tracer.node import TracerError, TracerProcess
    try:
        memory = parse_bytes(v["memory"]) if v["memory"] else None
    except argparse.ArgumentTypeError as e:
        return core._error(f"--memory: {e}")
    from services.wire import WireError
    try:
        tp = TracerProcess(v["server"], bind=v["bind"], advertise=v["advertise"], store=v["store"],
                           cache_dir=v["cache_dir"], memory_bytes=memory, threads=v["threads"],
                           tracer_id=v["id"], connect_timeout_s=v["retry"], curve_secret=v["curve_secret"],
                           curve_server_key=v["curve_server_key"], curve_clients=v["curve_clients"])
        reason = tp.run()
    except (TracerError, WireError) as e:
        return core._error(str(e), 1)
    except KeyboardInterrupt:
        return 130
    if not quiet:
        print(f"dosppm worker {tp.tracer_id}: {reason}", file=sys.stderr)
    return 0


def warm_kernels() -> None:
    """Compile every kernel a render uses (eye, photon, portal, gather) on
    a tiny two-chunk scene, so numba's cache holds them before any tracer
    starts its clock (tracers would otherwise each compile at once)."""
    from dosppm_core.scene import builtin
    from dosppm_core.chunks.store import ChunkStore
    from dosppm_core.scene.soup import SceneSource
    from dosppm_core.chunks.subdivide import subdivide

    from services.inproc import InProcessCluster
    scene = builtin.make("cornell-box")
    scene.camera.width = scene.camera.height = 16
    with tempfile.TemporaryDirectory(prefix="dosppm-warm-") as tmp:
        subdivide(SceneSource(scene), os.path.join(tmp, "s"), chunks=2)
        store = ChunkStore.open(os.path.join(tmp, "s"))
        settings = RenderSettings(photons_per_iteration=2048, photons_per_job=512, tile_pixels=64,
                                  threads=1)
        for gather in ("grid", "hash"):
            settings.gather = gather
            c = InProcessCluster(store, settings, tracers=1, min_photon_jobs=4)
            c.run(photons=4096)
            c.close()
