"""The `subdivide` subcommand; `cli.py` registers it.

    dosppm subdivide SCENE --budget 512MiB --out DIR [--chunks C] [--grid N]

SCENE is a built-in name, a .toml or Mitsuba .xml scene file, or a triangle
soup directory. Exit codes: 0 success, 2 bad input (one line on stderr
naming the file or field).
"""
from __future__ import annotations

import argparse
import re
import time

import numpy as np

_UNITS = {"": 1, "b": 1, "k": 1024, "kib": 1024, "m": 1024 ** 2, "mib": 1024 ** 2,
          "g": 1024 ** 3, "gib": 1024 ** 3}


def parse_bytes(text: str) -> int:
    """'512MiB', '1.5GiB', '64KiB', '1000000' -> bytes (binary units; K, M, G
    are read as KiB, MiB, GiB)."""
    m = re.fullmatch(r"\s*([0-9]*\.?[0-9]+(?:[eE][0-9]+)?)\s*([A-Za-z]*)\s*", text)
    unit = m.group(2).lower() if m else None
    if not m or unit not in _UNITS:
        raise argparse.ArgumentTypeError(
            f"bad size {text!r}: expected a number with an optional KiB, MiB or GiB suffix")
    value = int(float(m.group(1)) * _UNITS[unit])
    if value <= 0:
        raise argparse.ArgumentTypeError(f"bad size {text!r}: must be positive")
    return value


def _positive_int(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        value = 0
    if value < 1:
        raise argparse.ArgumentTypeError(f"must be a positive integer, got {text!r}")
    return value


def add_subdivide_parser(sub) -> argparse.ArgumentParser:
    from dosppm_core.chunks.subdivide import DEFAULT_GRID
    p = sub.add_parser(
        "subdivide", help="cut a scene into chunks that fit a memory budget (a chunk store)",
        description="Subdivide SCENE into box-shaped chunks (§4.1: binning, kd-tree, portals, "
                    "insertion) and write them as a chunk store in DIR.")
    p.add_argument("scene", help="built-in scene name, .toml or Mitsuba .xml file, or a soup directory")
    p.add_argument("--budget", type=str, metavar="SIZE",
                   help="memory per loaded chunk, BVH included, e.g. 512MiB (KiB, MiB, GiB)")
    p.add_argument("--chunks", type=_positive_int, metavar="C",
                   help="force exactly C chunks instead (a budget given too is then checked)")
    p.add_argument("--grid", type=_positive_int, default=DEFAULT_GRID, metavar="N",
                   help=f"bins of the uniform counting grid (default {DEFAULT_GRID})")
    p.add_argument("--out", required=True, metavar="DIR", help="the chunk store directory to write")
    p.set_defaults(func=cmd_subdivide)
    return p


def cmd_subdivide(args) -> int:
    from services.cli.render import _error
    from dosppm_core.scene.loaders import load_source
    from dosppm_core.scene.model import SceneError
    from dosppm_core.chunks.subdivide import format_bytes, subdivide
    try:
        budget = None if args.budget is None else parse_bytes(args.budget)
    except argparse.ArgumentTypeError as e:
        return _error(f"--budget: {e}")
    if budget is None and args.chunks is None:
        return _error("give --budget SIZE or --chunks C")
    t = time.perf_counter()
    try:
        source = load_source(args.scene)
        loaded = time.perf_counter() - t
        report = subdivide(source, args.out, budget_bytes=budget, grid=args.grid, chunks=args.chunks)
    except (SceneError, ValueError, OSError) as e:
        return _error(str(e))
    _print_report(report, loaded, budget, format_bytes)
    return 0


def _print_report(report, loaded_s: float, budget, format_bytes) -> None:
    from dosppm_core.chunks.store import ChunkStore
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


