"""The `dosppm` command line."""
from __future__ import annotations

import argparse
import os
import sys
import time
import warnings

from dosppm_core.scene.model import SceneError


def _error(msg: str, code: int = 2) -> int:
    print(f"dosppm: error: {msg}", file=sys.stderr)
    return code


def add_render_parser(sub) -> None:
    from dosppm_core.scene import builtin
    p = sub.add_parser("render", help="render a scene")
    p.add_argument("scene", nargs="?", default=builtin.DEFAULT,
                   help=f"built-in scene name, .toml or Mitsuba .xml file (default {builtin.DEFAULT})")
    stop = p.add_mutually_exclusive_group()
    stop.add_argument("--time", type=float, metavar="S", help="render for S seconds (default 30)")
    stop.add_argument("--photons", type=float, metavar="N", help="render until N photons are emitted")
    stop.add_argument("--iterations", type=int, metavar="K", help="render K iterations")
    p.add_argument("--out", default="out.exr", help="output EXR (a PNG preview is written beside it)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--gather", choices=("grid", "hash"), default="grid")
    p.add_argument("--alpha", type=float, default=0.7, help="radius reduction (eq. 1-2)")
    p.add_argument("--radius", type=float, help="initial radius in scene units (default: from scene and pixel size)")
    p.add_argument("--max-depth", type=int, default=10, help="surfaces a path may hit")
    p.add_argument("--photons-per-iteration", type=int, default=100_000)
    p.add_argument("--photon-batch", type=int, default=1_000_000, help="deposits per statistics update")
    p.add_argument("--width", type=int)
    p.add_argument("--height", type=int)
    p.add_argument("--threads", type=int, default=os.cpu_count() or 1)
    p.add_argument("--log", help="append JSON-lines progress records here")
    p.add_argument("--exposure", type=float, default=0.0, help="PNG preview exposure in stops")
    p.add_argument("--quiet", action="store_true")
    ooc = p.add_argument_group("out of core (OSPPM): any of these renders chunk by chunk")
    ooc.add_argument("--budget", metavar="SIZE", help="memory per chunk, BVH included (e.g. 512MiB)")
    ooc.add_argument("--chunks", type=int, metavar="C", help="force C chunks")
    ooc.add_argument("--memory", metavar="SIZE",
                     help="resident chunks at most this much (default: twice the budget or all)")
    ooc.add_argument("--schedule", choices=("pipelined", "drained"), default="pipelined",
                     help="pipelined: one sweep over the chunks per iteration, portal rays carried "
                          "over (§3.3); drained: every ray ends within its iteration, which "
                          "reproduces the unchunked image exactly")
    ooc.add_argument("--store-cache", metavar="DIR", default=_default_store_cache(),
                     help="where chunk stores made on the fly are kept (default %(default)s)")
    p.set_defaults(func=cmd_render)


def _default_store_cache() -> str:
    base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return os.path.join(base, "dosppm", "chunks")


def cmd_render(args) -> int:
    from dosppm_core.film import write_exr, write_png
    from services.progress import ProgressReporter, kernels_cached
    try:
        settings = render_settings(args)
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            renderer, describe = _make_renderer(args, settings)
        for w in caught:
            print(f"dosppm: warning: {w.message}", file=sys.stderr)
    except (SceneError, ValueError, OSError) as e:
        return _error(str(e))
    limit = _limit(args)
    say = (lambda *a: None) if args.quiet else (lambda *a: print(*a, file=sys.stderr))
    say(describe)
    if not kernels_cached():
        say("compiling kernels (first run on this machine; cached afterwards, about a minute)...")
    reporter = ProgressReporter(limit, args.log, quiet=args.quiet)
    interrupted = False
    try:
        while not _done(renderer, limit):
            reporter(renderer.run_iteration())
        if hasattr(renderer, "finish"):
            renderer.finish()   # OSPPM: trace the photons still queued at portals
    except KeyboardInterrupt:
        interrupted = True
    finally:
        reporter.close()
        renderer.close()
    _write_outputs(renderer, args.out, args.exposure, write_exr, write_png)
    p = renderer.progress()
    say(f"{'interrupted: ' if interrupted else ''}wrote {args.out} after {p.iteration} iterations, "
        f"{p.photons_emitted:,} photons, {p.seconds:.1f} s")
    return 130 if interrupted else 0


def render_settings(args, **overrides):
    """RenderSettings from the render flags (validated)."""
    from dosppm_core.modes.sppm import RenderSettings
    settings = RenderSettings(seed=args.seed, alpha=args.alpha, radius=args.radius,
                              max_depth=args.max_depth, gather=args.gather,
                              photons_per_iteration=args.photons_per_iteration,
                              photon_batch=args.photon_batch, threads=args.threads, **overrides)
    settings.validate()
    return settings


def _make_renderer(args, settings):
    """The single-process renderer, or OSPPM over a chunk store when the
    scene is a store or a soup, or chunking was asked for."""
    from dosppm_core.chunks.store import is_store
    from services.cli.chunks import parse_bytes
    from dosppm_core.scene.loaders import load_scene
    from dosppm_core.modes.sppm import Renderer
    from dosppm_core.scene.soupfile import is_soup
    chunked = is_store(args.scene) or is_soup(args.scene) or args.budget or args.chunks
    if not chunked:
        scene = load_scene(args.scene, width=args.width, height=args.height)
        return Renderer(scene, settings), (
            f"scene {scene.name}: {scene.triangle_count:,} triangles, {len(scene.lights.kind)} lights, "
            f"{scene.camera.width}x{scene.camera.height}")
    from dosppm_core.modes.osppm import OutOfCoreRenderer
    store = open_store(args)
    memory = _size("--memory", args.memory, parse_bytes)
    if memory is None and store.budget_bytes:
        memory = max(2 * store.budget_bytes, store.chunk_memory.max())
    cam = store.header.camera
    return OutOfCoreRenderer(store, settings, memory_bytes=memory,
                             pipelined=args.schedule == "pipelined"), (
        f"scene {store.header.name}: {store.source_triangles:,} triangles in {store.chunk_count} chunks "
        f"({store.path}), {len(store.header.lights.kind)} lights, {cam.width}x{cam.height}")


def open_store(args, default_budget: int = 512 * 2 ** 20):
    """The chunk store to render: `args.scene` itself when it is one,
    otherwise the scene subdivided on the fly (cached by key under
    `--store-cache`) at `--budget` (default `default_budget`) or into
    `--chunks`; `--width`/`--height` override its camera."""
    from dosppm_core.chunks.store import ChunkStore, is_store, open_or_subdivide
    from services.cli.chunks import parse_bytes
    from dosppm_core.scene.loaders import load_source
    budget = _size("--budget", args.budget, parse_bytes)
    if is_store(args.scene):
        store = ChunkStore.open(args.scene)
    else:
        if budget is None and args.chunks is None:
            budget = default_budget
        store = open_or_subdivide(load_source(args.scene), args.store_cache, budget=budget,
                                  chunks=args.chunks)
    for key in ("width", "height"):
        if getattr(args, key):
            setattr(store.header.camera, key, int(getattr(args, key)))
    return store


def _size(flag: str, text, parse) -> int | None:
    import argparse as _argparse
    if text is None:
        return None
    try:
        return parse(text)
    except _argparse.ArgumentTypeError as e:
        raise ValueError(f"{flag}: {e}") from None


def _limit(args) -> tuple[str, float]:
    if args.photons is not None:
        return ("photons", args.photons)
    if args.iterations is not None:
        return ("iterations", args.iterations)
    return ("seconds", args.time if args.time is not None else 30.0)


def _done(renderer, limit) -> bool:
    kind, value = limit
    p = renderer.progress()
    if p.iteration == 0:
        return False
    return {"seconds": p.seconds, "photons": p.photons_emitted,
            "iterations": p.iteration}[kind] >= value


def _write_outputs(renderer, out: str, exposure: float, write_exr, write_png) -> None:
    stats = renderer.stats
    h, w = stats.height, stats.width
    layers = {"radius": stats.radius.reshape(h, w).astype("float32"),
              "photon_count": stats.photon_count.reshape(h, w).astype("float32")}
    img = renderer.image()
    os.makedirs(os.path.dirname(os.path.abspath(out)), exist_ok=True)
    write_exr(out, img, layers)
    write_png(os.path.splitext(out)[0] + ".png", img, exposure=exposure)


def add_scenes_parser(sub) -> None:
    from dosppm_core.scene import generate
    p = sub.add_parser("scenes", help="list the built-in scenes, or generate a large one")
    p.set_defaults(func=cmd_scenes)
    generate.add_generate_arguments(p.add_subparsers(dest="scenes_command", metavar="{generate}"))


def cmd_scenes(args) -> int:
    from dosppm_core.scene import builtin
    for name, text in builtin.SCENES.items():
        mark = " (default)" if name == builtin.DEFAULT else ""
        print(f"{name:18s} {text}{mark}")
    print("generators: building (dosppm scenes generate building --help)")
    return 0


def add_bench_parser(sub) -> None:
    p = sub.add_parser("bench", help="measure tracing and statistics-update throughput")
    p.add_argument("scenes", nargs="*", default=None,
                   help="built-in names or scene files (default: the default scene)")
    p.add_argument("--mesh", action="append", default=[],
                   help="also bench this mesh file placed in glass in the Cornell box (repeatable)")
    p.add_argument("--photons", type=int, default=1_000_000)
    p.add_argument("--repeats", type=int, default=3)
    p.add_argument("--threads", type=int, default=os.cpu_count() or 1)
    p.add_argument("--json", help="write the results here")
    p.set_defaults(func=cmd_bench)


def cmd_bench(args) -> int:
    from services.evaluation import bench
    from dosppm_core.scene import builtin
    from dosppm_core.scene.loaders import load_scene
    try:
        scenes = [load_scene(s) for s in (args.scenes or [builtin.DEFAULT])]
        scenes += [builtin.cornell_with_mesh(m) for m in args.mesh]
    except (SceneError, OSError) as e:
        return _error(str(e))
    results = []
    for scene in scenes:
        print(f"benchmarking {scene.name} ({scene.triangle_count:,} triangles)...", file=sys.stderr)
        results.append(bench.bench_scene(scene, args.photons, args.repeats, args.threads))
    print(bench.report(results))
    if args.json:
        bench.write_json(args.json, results)
    return 0


def build_parser() -> argparse.ArgumentParser:
    return make_parser()[0]


def make_parser() -> tuple[argparse.ArgumentParser, argparse._SubParsersAction]:
    """The library's commands; the service's CLI (`services.cli`, the
    `dosppm` console script) adds its own to the same subparsers."""
    parser = argparse.ArgumentParser(prog="dosppm", description=__doc__)
    sub = parser.add_subparsers(dest="command", required=True)
    add_render_parser(sub)
    add_scenes_parser(sub)
    add_bench_parser(sub)
    from services.cli import tools as cli_tools
    cli_tools.add_reference_parser(sub)
    cli_tools.add_compare_parser(sub)
    cli_tools.add_evaluate_parser(sub)
    from services.cli import chunks as cli_chunks
    cli_chunks.add_subdivide_parser(sub)
    return parser, sub


def main(argv=None) -> int:
    args = build_parser().parse_args(argv)
    return args.func(args)


if __name__ == "__main__":
    sys.exit(main())
