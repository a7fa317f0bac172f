"""Starting the roles: `run_server` (the server, optionally with tracer
processes on this machine: `dosppm render`'s default mode), `run_tracer`
(one tracer: `dosppm worker`) and `warm_kernels` (compile the numba kernels
once, before any clock runs). Both roles take their settings as a dict of
the options in `services.config` and return an exit status."""
from __future__ import annotations

import json
import os
import subprocess
import sys
import tempfile
import time

from dosppm_core.chunks.pacing import default_chunk_memory
from dosppm_core.chunks.store import ChunkStore
from dosppm_core.chunks.subdivide import open_render_store, subdivide
from dosppm_core.modes.deadline import grace_s
from dosppm_core.scene import builtin
from dosppm_core.scene.model import SceneError
from dosppm_core.scene.soup import SceneSource
from dosppm_core.settings import RenderSettings
from services import config, transport
from services.cli.errors import EXIT_FAILED, EXIT_INTERRUPTED, EXIT_OK, fail, warnings_as_lines
from services.inproc import InProcessCluster
from dosppm_core.malloc import SERVER_MMAP_THRESHOLD_BYTES, return_large_blocks
from services.progress import COMPILING, ProgressReporter, kernels_cached, stderr_lines
from services.server import checkpoint
from services.server.node import ServerProcess
from services.server.options import Limits, ServerOptions
from services.tracer.node import TracerError, TracerOptions, TracerProcess
from services.wire import WireError

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def run_server(scene: str, v: dict, quiet: bool = False, spawn_tracers: int = 0) -> int:
    """Render `scene` as the server with settings `v` (the options of
    `config.SERVER`), after starting `spawn_tracers` tracer processes here."""
    say = stderr_lines(quiet)
    try:
        store = _open_store(scene, v)
        settings = config.render_settings(v, service=True, scene_hints=store.header.render_settings)
        http = _http(v["http"])
        resume = checkpoint.read(v["resume"], store.key) if v["resume"] else None
        if resume is not None:
            settings = _resumed_settings(settings, resume)
            resume["claimed_first_job"] = checkpoint.claim_job_ids(v["resume"], resume)
    except (SceneError, ValueError, OSError) as e:
        return fail(str(e))
    # Kernels compiled, the first time, before any clock starts and before
    # tracers are started, which then find them in the cache. In a child:
    # warming loads every kernel of every role (tracing, Embree), 70 MiB
    # the server would keep; it loads its own from the cache as it goes.
    if not kernels_cached():
        say(COMPILING)
        try:
            warm_kernels_apart()
        except RuntimeError as e:
            return fail(str(e))
    return_large_blocks(SERVER_MMAP_THRESHOLD_BYTES)      # dosppm_core/malloc.py
    limits = _limits(v)
    reporter = ProgressReporter(config.stop_limit(limits.seconds, limits.photons, limits.iterations),
                                v["log"], quiet=quiet)
    try:
        server = _server(store, settings, v, http, limits, reporter, resume, say)
    except Exception as e:   # zmq bind errors and the like: one line, not a traceback
        return fail(f"cannot start the server: {e}")
    cam = store.header.camera
    say(f"scene {store.header.name}: {store.source_triangles:,} triangles in {store.chunk_count} "
        f"chunk(s), {len(store.header.lights.kind)} lights, {cam.width}x{cam.height}")
    say(f"server {server.endpoint}" + (f", status {server.status_url}" if server.status_url else ""))
    # The tracers and this server share the machine: each tracer's chunks
    # get a share of it unless --memory says.
    memory = v.get("memory") or default_chunk_memory(spawn_tracers + 1, at_least=store.chunk_memory.max())
    tracers = _spawn_tracers(spawn_tracers, server.endpoint, store.path, v["threads"],
                             {"--memory": memory, "--queue-memory": v.get("queue_memory")})
    server.watch = lambda: _early_exit(tracers)
    try:
        summary = server.run()
    finally:
        reporter.close()
        _reap(tracers, _grace_left(server, limits))
    _write_summary(v["out"], summary)
    p = server.progress()
    say(f"{'interrupted: ' if server.interrupted else ''}wrote {v['out']} after {p.iteration} "
        f"iterations, {summary['photons_committed']:,} photons, {p.seconds:.1f} s")
    if server.failure:
        return fail(server.failure, EXIT_FAILED)
    return EXIT_INTERRUPTED if server.interrupted else EXIT_OK


def _open_store(scene: str, v: dict) -> ChunkStore:
    budget_bytes, chunks = config.chunking(v)
    with warnings_as_lines():
        return open_render_store(scene, v["store_cache"], budget_bytes, chunks, v["width"], v["height"],
                                 v.get("define"))


def _resumed_settings(settings: RenderSettings, doc: dict) -> RenderSettings:
    """The render settings saved in a checkpoint win over the flags: a
    resumed render goes on exactly as it began."""
    for k, value in doc["settings"].items():
        if hasattr(settings, k):
            setattr(settings, k, value)
    settings.validate()
    return settings


def _http(text: str):
    if text in (None, "", "off"):
        return None
    why = config.problem(config.option("http"), text)    # the rule a flag or DOSPPM_HTTP meets
    if why:
        raise ValueError(f"--http: {why}")
    host, _, port = text.rpartition(":")
    return host, int(port)


def _limits(v: dict) -> Limits:
    """The server stops at the first limit reached; with none given, after
    `config.SECONDS`."""
    limits = Limits(v["time"], v["photons"], v["iterations"])
    if limits.seconds is None and limits.photons is None and limits.iterations is None:
        limits.seconds = config.SECONDS
    return limits


def _server(store, settings, v: dict, http, limits: Limits, reporter, resume, say) -> ServerProcess:
    ckpt = v["checkpoint"] or v["resume"] or (os.path.splitext(v["out"])[0] + ".checkpoint" if v["out"] else None)
    options = ServerOptions(
        bind=v["bind"], http=http, out=v["out"], exposure=v["exposure"], limits=limits,
        snapshot_interval_s=v["snapshot_interval"], drain_timeout_s=v["drain_timeout"], threads=v["threads"],
        checkpoint_dir=ckpt, checkpoint_interval_s=v["checkpoint_interval"], ledger=v["ledger"],
        curve_secret=v["curve_secret"], curve_clients=v["curve_clients"],
        min_photon_jobs=v["min_photon_jobs"], min_tracers=v["min_tracers"],
        min_tracers_timeout_s=v["min_tracers_timeout"], tracer_timeout_s=v["tracer_timeout"],
        concurrent=v["concurrent"], client_batching=v["client_batching"],
        held_bytes=config.parse_bytes(v.get("queue_memory"), "--queue-memory"),
        gather_at=v.get("gather_at", "server"), hit_point_stride=v.get("hit_point_stride"),
        batch_growth=v["batch_growth"])
    return ServerProcess(store, settings, options, resume=resume, reporter=reporter, say=say)


def _write_summary(out: str, summary: dict) -> None:
    """OUT.json beside the image: the server's accounting of the run
    (photons emitted, completed and applied, path ends, per tracer)."""
    if not out:
        return
    with open(os.path.splitext(out)[0] + ".json", "w", encoding="utf-8") as f:
        json.dump(summary, f, indent=1, default=str)


def _spawn_tracers(n: int, endpoint: str, store_path: str, threads: int, limits: dict | None = None) -> list:
    """`n` tracer processes; `limits` ({"--memory": size, "--queue-memory":
    size}, None for the default) bound each one's memory."""
    per = max(1, threads // max(n, 1))
    flags = [x for flag, size in (limits or {}).items() if size for x in (flag, str(size))]
    cmd, env = _python_child("-m", "services.cli", "worker", "--server", endpoint, "--store", store_path,
                             "--threads", str(per), "--quiet", *flags)
    return [subprocess.Popen(cmd + ["--id", f"local-{i}"], env=env) for i in range(n)]


def _python_child(*args: str) -> tuple[list[str], dict]:
    """A Python command line running this very copy of dosppm, and its
    environment. `-P` keeps the working directory off `sys.path` (`-m` and
    `-c` put it first): run in a checkout, a child would otherwise import
    the checkout's source instead of the installed package, and compile
    kernels numba has cached for the other copy, inside the render's clock
    (issue 29), or run edited code beside an unedited server."""
    env = dict(os.environ, PYTHONPATH=os.pathsep.join(filter(None, [ROOT, os.environ.get("PYTHONPATH")])))
    return [sys.executable, "-P", *args], env


def _early_exit(tracers: list) -> str | None:
    """A tracer process that died before the render ended."""
    for p in tracers:
        code = p.poll()
        if code is not None and code != 0:
            return f"tracer process {p.pid} exited with status {code}"
    return None


# With a time limit: the tracers' moment to exit once told (they may be in
# the middle of a step or a chunk load; then they are killed: the image is
# written and they hold nothing more), and this process's own exit after
# them (measured 0.26 s).
REAP_S = 0.1
EXIT_S = 0.4


def _grace_left(server: ServerProcess, limits: Limits) -> float:
    """Seconds the tracers get to exit: with a time limit, REAP_S or what is
    left of its grace but EXIT_S if less (0.1 s at least); otherwise 10 s."""
    if limits.seconds is None or server.started_at is None:
        return 10.0
    end = server.started_at + limits.seconds + grace_s(limits.seconds)
    return min(REAP_S, max(0.1, end - time.monotonic() - EXIT_S))


def _reap(tracers: list, timeout_s: float = 10.0) -> None:
    deadline = time.monotonic() + timeout_s
    for p in tracers:
        try:
            p.wait(max(0.1, deadline - time.monotonic()))
        except subprocess.TimeoutExpired:
            p.kill()
            p.wait()


def run_tracer(v: dict, quiet: bool = False) -> int:
    """Serve as one tracer with settings `v` (the options of
    `config.TRACER`) until the server ends the render."""
    say = stderr_lines(quiet)
    try:
        memory = config.parse_bytes(v["memory"], "--memory")
        queue_memory = config.parse_bytes(v["queue_memory"], "--queue-memory")
    except ValueError as e:
        return fail(str(e))
    # Kernels are compiled before the tracer registers: a tracer busy
    # compiling sends no heartbeats and would be evicted. (Cached kernels
    # load at the first job in about a second, well within the timeout.)
    if not kernels_cached():
        say(COMPILING)
        warm_kernels()
    try:
        tp = TracerProcess(TracerOptions(
            v["server"], bind=v["bind"], advertise=v["advertise"], store=v["store"], cache_dir=v["cache_dir"],
            memory_bytes=memory, queue_memory_bytes=queue_memory, threads=v["threads"], tracer_id=v["id"],
            connect_timeout_s=v["retry"], curve_secret=v["curve_secret"], curve_server_key=v["curve_server_key"],
            curve_clients=v["curve_clients"]), say=say)
        reason = tp.run()
    except (TracerError, WireError, transport.TransportError) as e:   # a bind refused, say
        return fail(str(e), EXIT_FAILED)
    except KeyboardInterrupt:
        return EXIT_INTERRUPTED
    say(f"tracer {tp.tracer_id}: {reason}")
    return EXIT_OK


def warm_kernels_apart() -> None:
    """`warm_kernels` in a child process: the cache is written, and this
    process loads only the kernels it calls."""
    cmd, env = _python_child("-c", "from services.local import warm_kernels; warm_kernels()")
    done = subprocess.run(cmd, env=env, capture_output=True, text=True)
    if done.returncode != 0:       # the render compiles as it goes instead
        lines = (done.stderr or "").strip().splitlines()
        raise RuntimeError(f"compiling the kernels failed: {lines[-1] if lines else done.returncode}")


def warm_kernels() -> None:
    """Compile every kernel a render uses (eye, photon, portal, gather) on
    a tiny two-chunk scene, so numba's cache holds them before any tracer
    starts its clock (tracers would otherwise each compile at once)."""
    scene = builtin.make("cornell-caustic")       # glass: eye steps of a few paths at its end
    scene.camera.width = scene.camera.height = 96
    with tempfile.TemporaryDirectory(prefix="dosppm-warm-") as tmp:
        subdivide(SceneSource(scene), os.path.join(tmp, "s"), chunks=2)
        store = ChunkStore.open(os.path.join(tmp, "s"))
        # Eye tiles on both sides of paths.SERIAL_BELOW: small batches run
        # the one-thread kernels, large ones the parallel ones.
        for gather, tile in (("grid", 64), ("hash", 64), ("grid", 96 * 96)):
            settings = RenderSettings(photons_per_iteration=2048, photons_per_job=512, tile_pixels=tile,
                                      threads=1, gather=gather)
            c = InProcessCluster(store, settings, tracers=1, min_photon_jobs=4)
            c.run(photons=4096)
            c.close()
