"""`dosppm scenes`: list the built-in scenes, or generate a large one.

    dosppm scenes
    dosppm scenes generate building --triangles 20M --lights 600 --out building/

Values of `generate` are parsed here, not by argparse, so that a bad one is
a one-line error (exit status 2).
"""
from __future__ import annotations

import math

from dosppm_core.scene import builtin, generate
from dosppm_core.scene.generate import BuildingSpec
from dosppm_core.scene.model import SceneError
from services.cli.errors import EXIT_OK, fail
from services.config import parse_int

_SUFFIX = {"k": 1_000, "K": 1_000, "M": 1_000_000}


def parse_count(text: str, what: str = "--triangles") -> int:
    """'20M', '100k', '1.5M', '250000' or '250_000' as a positive integer."""
    s = str(text).strip().replace("_", "")
    mult = _SUFFIX.get(s[-1:], 1)
    if mult != 1:
        s = s[:-1]
    try:
        value = float(s) * mult
    except ValueError:
        raise SceneError(f"{what}: expected a count such as 250000, 100k or 20M, got {text!r}") from None
    if not (math.isfinite(value) and value >= 1 and value == int(value)):
        raise SceneError(f"{what}: expected a positive whole count, got {text!r}")
    return int(value)


def parse_rooms(text: str) -> tuple[int, int]:
    """'8x6' as (rows, cols)."""
    parts = str(text).lower().split("x")
    try:
        rows, cols = (int(p) for p in parts)
    except ValueError:
        raise SceneError(f"--rooms: expected ROWSxCOLS such as 8x8, got {text!r}") from None
    if rows < 1 or cols < 1:
        raise SceneError(f"--rooms: rows and columns must be >= 1, got {text!r}")
    return rows, cols


def add_parser(sub) -> None:
    p = sub.add_parser("scenes", help="list the built-in scenes, or generate a large one")
    p.set_defaults(func=run)
    _add_generate_parser(p.add_subparsers(dest="scenes_command", metavar="{generate}"))


def _add_generate_parser(scenes_sub) -> None:
    spec = BuildingSpec()
    gen = scenes_sub.add_parser("generate", help="generate a large procedural scene as a triangle soup")
    kinds = gen.add_subparsers(dest="generator", required=True, metavar="{building}")
    p = kinds.add_parser("building", help="rooms with doors, ceiling lights, furniture and glass",
                         description=generate.__doc__.split("\n\n")[0])
    p.add_argument("--triangles", help=f"target triangle count, e.g. 250k or 20M (default {spec.triangles:,})")
    p.add_argument("--lights", help=f"ceiling area lights (default {spec.lights})")
    p.add_argument("--rooms", help="ROWSxCOLS rooms per floor (default: about 5 lights a room)")
    p.add_argument("--floors", help=f"storeys (default {spec.floors})")
    p.add_argument("--seed", help=f"default {spec.seed}")
    p.add_argument("--width", help=f"default {spec.width}")
    p.add_argument("--height", help=f"default {spec.height}")
    p.add_argument("--out", help="soup directory to write (required)")
    p.set_defaults(func=run_generate)


def run(args) -> int:
    for name, text in builtin.SCENES.items():
        mark = " (default)" if name == builtin.DEFAULT else ""
        print(f"{name:18s} {text}{mark}")
    print("generators: building (dosppm scenes generate building --help)")
    return EXIT_OK


def run_generate(args) -> int:
    try:
        if not args.out:
            raise ValueError("--out: name the soup directory to write")
        params = _building_params(args)
        report = generate.generate_building(args.out, **params)
    except (ValueError, OSError) as e:      # SceneError is a ValueError
        return fail(str(e))
    rate = report.triangles / max(report.seconds, 1e-9)
    print(f"building: {report.triangles:,} triangles (target {params['triangles']:,}), "
          f"{report.lights} lights, {report.rooms} rooms")
    print(f"wrote {report.path}: {report.bytes:,} bytes in {report.seconds:.1f} s "
          f"({rate / 1e6:.2f}M triangles/s), hash {report.content_hash[:16]}")
    return EXIT_OK


# How each flag of `generate building` is read (a bad value: ValueError naming the flag).
_BUILDING_FLAGS = {
    "triangles": parse_count,
    "lights": lambda text: parse_count(text, "--lights"),
    "rooms": parse_rooms,
    "floors": lambda text: parse_int(text, "--floors", 1),
    "seed": lambda text: parse_int(text, "--seed", 0),
    "width": lambda text: parse_int(text, "--width", 1),
    "height": lambda text: parse_int(text, "--height", 1),
}


def _building_params(args) -> dict:
    """The building's parameters: those given, parsed, else `BuildingSpec`'s."""
    spec = BuildingSpec()
    return {name: getattr(spec, name) if getattr(args, name) is None else read(getattr(args, name))
            for name, read in _BUILDING_FLAGS.items()}
