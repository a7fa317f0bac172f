"""`dosppm render`: render a scene in one of three modes.

    dosppm render [SCENE] [--tracers N]    dosppm: a server and N tracer processes here (default)
    dosppm render SCENE --mode sppm        one process, the whole scene
    dosppm render SCENE --mode osppm       one process, the scene chunk by chunk

Every mode writes OUT (EXR, with radius and photon-count layers) and a PNG
preview beside it; the service also writes OUT.json, its accounting of the
run. A store or a triangle soup is always rendered chunk by chunk.
"""
from __future__ import annotations

import argparse
import dataclasses
import os
import time

from dosppm_core.chunks.store import is_store
from dosppm_core.chunks.subdivide import open_render_store
from dosppm_core.film import write_exr, write_png
from dosppm_core.modes.deadline import Deadline
from dosppm_core.modes.osppm import OutOfCoreRenderer
from dosppm_core.modes.sppm import Renderer
from dosppm_core.scene import builtin
from dosppm_core.scene.loaders import load_scene
from dosppm_core.scene.model import SceneError
from dosppm_core.scene.soupfile import is_soup
from dosppm_core.settings import GATHER_AT_TRACERS_PHOTONS_PER_JOB, SERVICE_JOB_SIZES, RenderSettings
from services import config
from services.cli.errors import EXIT_INTERRUPTED, EXIT_OK, fail, warnings_as_lines
from services.local import run_server, warm_kernels
from services.progress import COMPILING, ProgressReporter, kernels_cached, stderr_lines

MODES = ("dosppm", "sppm", "osppm")
# Photons per job is the one setting whose default depends on the mode.
_RENDER = tuple(dataclasses.replace(o, default=None, help=(
    f"photons per photon job (default {RenderSettings().photons_per_job} in one process, "
    f"{SERVICE_JOB_SIZES['photons_per_job']} in the service, {GATHER_AT_TRACERS_PHOTONS_PER_JOB} "
    f"gathering at the tracers)"))
    if o.name == "photons_per_job" else o for o in config.RENDER)
# The local server's status page: loopback, on any free port.
_SERVICE = tuple(dataclasses.replace(o, default="127.0.0.1:0") if o.name == "http" else o
                 for o in config.SERVICE)
# The server's settings the render flags give; the others keep the server's defaults.
_SERVER_FLAGS = config.LIMITS + _RENDER + config.CHUNKING + config.OPTIMISATIONS + _SERVICE


def add_parser(sub) -> None:
    p = sub.add_parser("render", help="render a scene", description=__doc__,
                       formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("scene", nargs="?", default=builtin.DEFAULT,
                   help=f"built-in scene name, .toml or Mitsuba .xml file, chunk store or soup directory "
                        f"(default {builtin.DEFAULT})")
    p.add_argument("--mode", choices=MODES, default="dosppm",
                   help="dosppm: a server and tracer processes on this machine (default); "
                        "sppm: one process, whole scene; osppm: one process, chunk by chunk")
    config.add_options(p.add_mutually_exclusive_group(), config.LIMITS)
    config.add_options(p, _RENDER)
    config.add_scene_parameters(p)
    p.add_argument("--quiet", action="store_true")
    ooc = p.add_argument_group("chunks (--mode osppm and dosppm)")
    config.add_options(ooc, config.CHUNKING)
    ooc.add_argument("--memory", metavar="SIZE", type=config.size,
                     help="resident chunks at most this much: osppm's one process (default: twice the "
                          "budget or all), each dosppm tracer (default: its share of the machine's "
                          "memory or its cgroup limit, less ~200MiB and the queue: all its chunks when "
                          "they fit)")
    ooc.add_argument("--queue-memory", metavar="SIZE", type=config.size,
                     help="queued rays at most this much when more chunks than fit make the renderer "
                          "queue more to hide their loads; the server's deposits held for photon jobs "
                          "in flight too (default: 1/16 of the machine's memory or its cgroup "
                          "limit, 32MiB to 1GiB)")
    ooc.add_argument("--schedule", choices=("pipelined", "drained"), default="pipelined",
                     help="osppm: pipelined: one sweep over the chunks per iteration, portal rays "
                          "carried over (§3.3); drained: every ray ends within its iteration, which "
                          "reproduces the unchunked image exactly")
    service = p.add_argument_group("the render service (--mode dosppm, the default)")
    service.add_argument("--tracers", type=config.positive_int, help="tracer processes (default: one per core)")
    config.add_options(service, _SERVICE)
    optimisations = p.add_argument_group("the paper's optimisations (Figure 15; --no-cull in every mode)")
    config.add_options(optimisations, config.OPTIMISATIONS)
    p.set_defaults(func=run)


def run(args) -> int:
    if args.mode == "dosppm":
        return _run_service(args)
    if args.mode == "sppm" and (args.budget or args.chunks):
        return fail("--mode sppm renders the whole scene: drop --budget/--chunks")
    return _run_here(args)


def _run_service(args) -> int:
    """A server in this process and `--tracers` tracer processes."""
    n = args.tracers or os.cpu_count() or 1
    values = {o.name: o.default for o in config.SERVER}
    values.update({o.name: getattr(args, o.name) for o in _SERVER_FLAGS})
    values.update(bind="tcp://127.0.0.1:*", min_tracers=n, memory=args.memory, queue_memory=args.queue_memory,
                  define=config.scene_parameters(args))
    return run_server(args.scene, values, quiet=args.quiet, spawn_tracers=n)


def _run_here(args) -> int:
    """SPPM or OSPPM in this process, iteration by iteration until the limit."""
    say = stderr_lines(args.quiet)
    try:
        with warnings_as_lines():
            renderer, describe = _make_renderer(args)
    except (SceneError, ValueError, OSError) as e:
        return fail(str(e))
    limit = config.stop_limit(args.time, args.photons, args.iterations)
    say(describe)
    # Load the kernels (compile them, the first time) before the render's
    # clock starts: the time limit and the photons/s are the render's own.
    if not kernels_cached():
        say(COMPILING)
    warm_kernels()
    reporter = ProgressReporter(limit, args.log, quiet=args.quiet)
    interrupted = False
    # A time limit is a deadline: the image is written within its grace.
    deadline = Deadline.after(limit[1]) if limit[0] == "seconds" else None
    try:
        while not _done(renderer, limit, deadline):
            reporter(renderer.run_iteration(deadline))
        if hasattr(renderer, "finish"):
            renderer.finish(_drain_lines(say), deadline)   # OSPPM: the photons still queued at portals
    except KeyboardInterrupt:
        interrupted = True
    finally:
        reporter.close()
        renderer.close()
    _write_outputs(renderer, args.out, args.exposure)
    p = renderer.progress()
    say(f"{'interrupted: ' if interrupted else ''}wrote {args.out} after {p.iteration} iterations, "
        f"{p.photons_emitted:,} photons, {p.seconds:.1f} s")
    return EXIT_INTERRUPTED if interrupted else EXIT_OK


def _drain_lines(say, every_s: float = 10.0):
    """OSPPM's drain report: out of core it can take many sweeps past the
    limit, so a line every `every_s` says what is left rather than nothing."""
    t0 = last = time.monotonic()

    def report(rays: int, sweeps: int) -> None:
        nonlocal last
        now = time.monotonic()
        if now - last >= every_s and rays:
            last = now
            say(f"draining: {rays:,} rays still queued at portals after {sweeps} sweeps, {now - t0:.0f} s")
    return report


def _make_renderer(args):
    """The single-process renderer, or OSPPM over a chunk store when asked
    for, or when the scene is a store or a soup; and a line describing it.
    The settings are the flags', then the scene file's integrator's."""
    if not (args.mode == "osppm" or is_store(args.scene) or is_soup(args.scene)):
        scene = load_scene(args.scene, config.scene_parameters(args), width=args.width, height=args.height)
        settings = config.render_settings(vars(args), scene_hints=scene.render_settings)
        return Renderer(scene, settings), (
            f"scene {scene.name}: {scene.triangle_count:,} triangles, {len(scene.lights.kind)} lights, "
            f"{scene.camera.width}x{scene.camera.height}")
    budget_bytes, chunks = config.chunking(vars(args))
    memory = config.parse_bytes(args.memory, "--memory")
    store = open_render_store(args.scene, args.store_cache, budget_bytes, chunks, args.width, args.height,
                              config.scene_parameters(args))
    settings = config.render_settings(vars(args), scene_hints=store.header.render_settings)
    if memory is None and store.budget_bytes:
        memory = max(2 * store.budget_bytes, store.chunk_memory.max())
    cam = store.header.camera
    queue_memory = config.parse_bytes(args.queue_memory, "--queue-memory")
    return OutOfCoreRenderer(store, settings, memory_bytes=memory, queue_memory_bytes=queue_memory,
                             pipelined=args.schedule == "pipelined"), (
        f"scene {store.header.name}: {store.source_triangles:,} triangles in {store.chunk_count} chunks "
        f"({store.path}), {len(store.header.lights.kind)} lights, {cam.width}x{cam.height}")


def _done(renderer, limit, deadline) -> bool:
    kind, value = limit
    p = renderer.progress()
    if p.iteration == 0:
        return False
    if deadline is not None:
        return not renderer.worth_an_iteration(deadline)
    return {"seconds": p.seconds, "photons": p.photons_emitted,
            "iterations": p.iteration}[kind] >= value


def _write_outputs(renderer, out: str, exposure: float) -> None:
    stats = renderer.stats
    h, w = stats.height, stats.width
    layers = {"radius": stats.radius.reshape(h, w).astype("float32"),
              "photon_count": stats.photon_count.reshape(h, w).astype("float32")}
    img = renderer.image()
    os.makedirs(os.path.dirname(os.path.abspath(out)), exist_ok=True)
    write_exr(out, img, layers)
    write_png(os.path.splitext(out)[0] + ".png", img, exposure=exposure)
