"""`dosppm subdivide`: cut a scene into a chunk store.

    dosppm subdivide SCENE --budget 512MiB --out DIR [--chunks C] [--grid N] [--memory SIZE]

SCENE is a built-in name, a .toml or Mitsuba .xml scene file, or a triangle
soup directory. Exit codes: 0 success, 2 bad input (one line on stderr
naming the file or field).
"""
from __future__ import annotations

import time

import numpy as np

from dosppm_core.chunks.store import ChunkStore
from dosppm_core.chunks.subdivide import DEFAULT_GRID, format_bytes, subdivide
from dosppm_core.scene.loaders import load_source
from dosppm_core.scene.model import SceneError
from services import config
from services.cli.errors import EXIT_OK, fail
from services.config import parse_bytes, positive_int, size


def add_parser(sub) -> None:
    p = sub.add_parser(
        "subdivide", help="cut a scene into chunks that fit a memory budget (a chunk store)",
        description="Subdivide SCENE into box-shaped chunks (§4.1: binning, kd-tree, portals, "
                    "insertion) and write them as a chunk store in DIR.")
    p.add_argument("scene", help="built-in scene name, .toml or Mitsuba .xml file, or a soup directory")
    p.add_argument("--budget", type=size, metavar="SIZE",
                   help="memory per loaded chunk, BVH included, e.g. 512MiB (KiB, MiB, GiB)")
    p.add_argument("--chunks", type=positive_int, metavar="C",
                   help="force exactly C chunks instead (a budget given too is then checked)")
    p.add_argument("--grid", type=positive_int, default=DEFAULT_GRID, metavar="N",
                   help=f"bins of the uniform counting grid (default {DEFAULT_GRID})")
    p.add_argument("--memory", type=size, metavar="SIZE",
                   help="the subdivider's own working memory, besides one chunk being written "
                        "(about 1.5x --budget): sets how much of the scene is read at a time "
                        "(default: blocks of 1M triangles, about 200MiB)")
    p.add_argument("--out", required=True, metavar="DIR", help="the chunk store directory to write")
    config.add_scene_parameters(p)
    p.set_defaults(func=run)


def run(args) -> int:
    try:
        budget = parse_bytes(args.budget, "--budget")
        memory = parse_bytes(args.memory, "--memory")
    except ValueError as e:
        return fail(str(e))
    if budget is None and args.chunks is None:
        return fail("give --budget SIZE or --chunks C")
    t = time.perf_counter()
    try:
        source = load_source(args.scene, config.scene_parameters(args))
        loaded = time.perf_counter() - t
        report = subdivide(source, args.out, budget_bytes=budget, grid=args.grid, chunks=args.chunks,
                           memory_bytes=memory)
    except (SceneError, ValueError, OSError) as e:
        return fail(str(e))
    _print_report(report, loaded, budget)
    return EXIT_OK


def _print_report(report, loaded_s: float, budget: int | None) -> None:
    store = ChunkStore.open(report.path)
    tri = report.chunk_triangles
    print(f"{report.path}: {report.chunk_count} chunks from {report.source_triangles:,} triangles "
          f"(grid {'x'.join(map(str, report.grid))}, {len(store.portals)} portals)")
    print(f"triangles per chunk: min {tri.min():,}  median {int(np.median(tri)):,}  max {tri.max():,}; "
          f"duplicated {100 * report.duplicated_fraction:.2f}%")
    mem = store.chunk_memory
    limit = f" (budget {format_bytes(budget)})" if budget else ""
    print(f"memory per loaded chunk: max {format_bytes(mem.max())}{limit}")
    stages = "  ".join(f"{k} {v:.2f} s" for k, v in [("loading", loaded_s), *report.seconds.items()])
    print(f"times: {stages}")
