"""`dosppm bench`: tracing and statistics-update throughput of scenes (the
measurement is `harness.bench`; benchmarks/core.sh runs it)."""
from __future__ import annotations

import sys

from dosppm_core.scene import builtin
from dosppm_core.scene.loaders import load_scene
from dosppm_core.scene.model import SceneError
from harness import bench
from services import config
from services.cli.errors import EXIT_OK, fail


def add_parser(sub) -> None:
    p = sub.add_parser("bench", help="measure tracing and statistics-update throughput")
    p.add_argument("scenes", nargs="*", default=None,
                   help="built-in names or scene files (default: the default scene)")
    p.add_argument("--mesh", action="append", default=[],
                   help="also bench this mesh file placed in glass in the Cornell box (repeatable)")
    p.add_argument("--photons", type=config.positive_int, default=1_000_000)
    p.add_argument("--repeats", type=config.positive_int, default=3)
    p.add_argument("--threads", type=config.positive_int, default=config.THREADS)
    p.add_argument("--json", help="write the results here")
    p.set_defaults(func=run)


def run(args) -> int:
    try:
        scenes = [load_scene(s) for s in (args.scenes or [builtin.DEFAULT])]
        scenes += [builtin.cornell_with_mesh(m) for m in args.mesh]
    except (SceneError, OSError) as e:
        return fail(str(e))
    results = []
    for scene in scenes:
        print(f"benchmarking {scene.name} ({scene.triangle_count:,} triangles)...", file=sys.stderr)
        results.append(bench.bench_scene(scene, args.photons, args.repeats, args.threads))
    print(bench.report(results))
    if args.json:
        bench.write_json(args.json, results)
    return EXIT_OK
