"""`dosppm reference`: a reference image rendered by Mitsuba 3.

    dosppm reference SCENE --spp N --out ref.exr [--max-depth D]
                     [--integrator path|ptracer] [--seed K] [--width W --height H]

Exit codes: 0 success, 1 the reference renderer is missing or failed,
2 bad input (an unreadable scene); each error is one line on stderr that
names the file.
"""
from __future__ import annotations

import time

from dosppm_core.film import FilmError, write_exr
from dosppm_core.scene import loaders
from dosppm_core.scene.model import SceneError
from harness import mitsuba_probe, reference
from services import config
from services.cli.errors import EXIT_FAILED, EXIT_OK, fail
from services.config import non_negative_int, positive_int


def add_parser(sub) -> None:
    p = sub.add_parser(
        "reference", help="render a reference image with Mitsuba 3",
        description="Render SCENE with Mitsuba 3's path tracer (or light tracer) "
                    "into a linear float32 EXR, for comparison with SPPM renders.")
    p.add_argument("scene", help="built-in scene name, .toml or Mitsuba .xml file")
    p.add_argument("--spp", type=positive_int, required=True, help="samples per pixel")
    p.add_argument("--out", required=True, help="output EXR path")
    p.add_argument("--max-depth", type=int, default=reference.DEFAULT_MAX_DEPTH,
                   help="maximum bounces on a light path, as in our renderer "
                        f"(Mitsuba max_depth = this + 1; negative: unbounded; "
                        f"default {reference.DEFAULT_MAX_DEPTH})")
    p.add_argument("--integrator", choices=reference.INTEGRATORS, default="path")
    config.add_scene_parameters(p)
    p.add_argument("--seed", type=non_negative_int, default=0)
    p.add_argument("--width", type=positive_int, help="override the camera's width")
    p.add_argument("--height", type=positive_int, help="override the camera's height")
    p.add_argument("--variant", default=None,
                   help="Mitsuba variant (default: llvm_ad_rgb if it works here, else scalar_rgb)")
    p.set_defaults(func=run)


def run(args) -> int:
    try:
        params = config.scene_parameters(args)     # -D: only when given
        scene = loaders.load_scene(args.scene, width=args.width, height=args.height,
                                   **({"params": params} if params else {}))
    except (SceneError, OSError) as exc:
        return fail(str(exc))
    start = time.perf_counter()
    try:
        variant = args.variant or mitsuba_probe.best_variant()
        image = reference.render_reference(scene, args.spp, args.max_depth, args.integrator,
                                           args.seed, variant)
    except reference.ReferenceRenderError as exc:
        return fail(str(exc), EXIT_FAILED)
    try:
        write_exr(args.out, image)
    except FilmError as exc:
        return fail(str(exc))
    h, w = image.shape[:2]
    print(f"wrote {args.out} ({w}x{h}, {args.spp} spp, {args.integrator}, {variant}, "
          f"{time.perf_counter() - start:.1f} s)")
    return EXIT_OK
