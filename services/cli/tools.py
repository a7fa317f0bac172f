"""The `reference` and `compare` subcommands; `cli.py` registers them.

    dosppm reference SCENE --spp N --out ref.exr [--max-depth D]
                     [--integrator path|ptracer] [--seed K] [--width W --height H]
    dosppm compare A.exr B.exr [--diff diff.png] [--json]

Exit codes: 0 success, 1 the reference renderer is missing or failed,
2 bad input (unreadable scene or image, mismatched sizes, NaN pixels); each
error is one line on stderr that names the file.
"""
from __future__ import annotations

import argparse
import json
import sys
import time

import numpy as np

EXIT_OK, EXIT_FAILED, EXIT_BAD_INPUT = 0, 1, 2


def _positive_int(text: str) -> int:
    value = int(text)
    if value < 1:
        raise argparse.ArgumentTypeError(f"must be a positive integer, got {text}")
    return value


def _error(command: str, message: str, code: int) -> int:
    print(f"dosppm {command}: {message}", file=sys.stderr)
    return code


# -- dosppm reference --------------------------------------------------------
def add_reference_parser(subparsers) -> argparse.ArgumentParser:
    from dosppm_core.reference import DEFAULT_MAX_DEPTH, INTEGRATORS
    p = subparsers.add_parser(
        "reference", help="render a reference image with Mitsuba 3",
        description="Render SCENE with Mitsuba 3's path tracer (or light tracer) "
                    "into a linear float32 EXR, for comparison with SPPM renders.")
    p.add_argument("scene", help="built-in scene name, .toml or Mitsuba .xml file")
    p.add_argument("--spp", type=_positive_int, required=True, help="samples per pixel")
    p.add_argument("--out", required=True, help="output EXR path")
    p.add_argument("--max-depth", type=int, default=DEFAULT_MAX_DEPTH,
                   help="maximum bounces on a light path, as in our renderer "
                        f"(Mitsuba max_depth = this + 1; negative: unbounded; "
                        f"default {DEFAULT_MAX_DEPTH})")
    p.add_argument("--integrator", choices=INTEGRATORS, default="path")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--width", type=_positive_int, help="override the camera's width")
    p.add_argument("--height", type=_positive_int, help="override the camera's height")
    p.add_argument("--variant", default=None,
                   help="Mitsuba variant (default: llvm_ad_rgb if it works here, else scalar_rgb)")
    p.set_defaults(func=run_reference)
    return p


def run_reference(args) -> int:
    from dosppm_core.scene import loaders
    from dosppm_core import reference
    from dosppm_core.film import FilmError, write_exr
    from dosppm_core.scene.model import SceneError
    try:
        scene = loaders.load_scene(args.scene, width=args.width, height=args.height)
    except (SceneError, OSError) as exc:
        return _error("reference", str(exc), EXIT_BAD_INPUT)
    start = time.perf_counter()
    try:
        variant = args.variant or reference.best_variant()
        image = reference.render_reference(scene, args.spp, args.max_depth, args.integrator,
                                           args.seed, variant)
    except reference.ReferenceRenderError as exc:
        return _error("reference", str(exc), EXIT_FAILED)
    try:
        write_exr(args.out, image)
    except FilmError as exc:
        return _error("reference", str(exc), EXIT_BAD_INPUT)
    h, w = image.shape[:2]
    print(f"wrote {args.out} ({w}x{h}, {args.spp} spp, {args.integrator}, {variant}, "
          f"{time.perf_counter() - start:.1f} s)")
    return EXIT_OK


# -- dosppm compare ----------------------------------------------------------
def add_compare_parser(subparsers) -> argparse.ArgumentParser:
    p = subparsers.add_parser(
        "compare", help="error metrics of one EXR against a reference EXR",
        description="Print RMSE, relMSE and mean-luminance bias of A against the "
                    "reference B, one `name value` per line.")
    p.add_argument("a", help="the image to judge (EXR)")
    p.add_argument("b", help="the reference (EXR)")
    p.add_argument("--diff", help="write a false-colour relative-difference PNG here")
    p.add_argument("--json", action="store_true",
                   help="print one JSON object instead of `name value` lines")
    p.set_defaults(func=run_compare)
    return p


def run_compare(args) -> int:
    from dosppm_core import metrics
    from dosppm_core.film import FilmError, read_exr
    images = []
    for path in (args.a, args.b):
        try:
            rgb = read_exr(path)[0]
        except FilmError as exc:
            return _error("compare", str(exc), EXIT_BAD_INPUT)
        bad = int(np.sum(~np.isfinite(rgb)))
        if bad:
            return _error("compare", f"{path}: contains NaN or Inf ({bad} values)", EXIT_BAD_INPUT)
        images.append(rgb)
    a, b = images
    if a.shape != b.shape:
        return _error("compare", f"{args.a}: size {a.shape[1]}x{a.shape[0]} differs from "
                                 f"{args.b}: {b.shape[1]}x{b.shape[0]}", EXIT_BAD_INPUT)
    try:
        result = _compare_metrics(metrics, a, b)
        if args.diff:
            result["diff_scale"] = metrics.difference_png(args.diff, a, b)
    except (ValueError, FilmError) as exc:
        return _error("compare", str(exc), EXIT_BAD_INPUT)
    _print_metrics(result, args)
    return EXIT_OK


def _compare_metrics(metrics, a: np.ndarray, b: np.ndarray) -> dict:
    result = {"rmse": metrics.rmse(a, b), "relmse": metrics.relmse(a, b)}
    # A black reference has no relative bias; report it as missing, not fail.
    try:
        result["mean_luminance_bias"] = metrics.mean_luminance_bias(a, b)
    except ValueError:
        result["mean_luminance_bias"] = None
    return result


def _print_metrics(result: dict, args) -> None:
    if args.json:
        print(json.dumps({"a": args.a, "b": args.b, **result}))
        return
    for name, value in result.items():
        print(f"{name} {'nan' if value is None else f'{value:.6g}'}")


# -- dosppm evaluate ---------------------------------------------------------
def add_evaluate_parser(subparsers) -> argparse.ArgumentParser:
    from services.evaluation.evaluate import METHODS, SUITES
    p = subparsers.add_parser(
        "evaluate", help="speed against accuracy: every method on a suite of scenes",
        description="Render each scene of SUITE with each method, stopped at 1/8, 1/4, 1/2 "
                    "and all of the time budget, and score every stop against the scene's "
                    "Mitsuba 3 reference (rendered once, then cached). Writes results.json, "
                    "results.csv, summary.md and, with matplotlib, the charts.")
    p.add_argument("suite", choices=sorted(SUITES), help="the suite of scenes")
    p.add_argument("--budget-s", type=float, default=20.0,
                   help="render seconds per method and scene (default 20)")
    p.add_argument("--out", default="evaluation", help="output folder (default ./evaluation)")
    p.add_argument("--method", action="append", choices=sorted(METHODS),
                   help="only this method (repeatable; default: the suite's)")
    p.add_argument("--scene", action="append", help="only this scene of the suite (repeatable)")
    p.add_argument("--reference-cache", help="where references are kept "
                                             "(default ~/.cache/dosppm/references)")
    p.add_argument("--reference-spp-scale", type=float, default=1.0,
                   help="scale the suite's reference sample counts (quick looks: 0.1)")
    p.add_argument("--seed", type=int, default=1)
    p.set_defaults(func=run_evaluate)
    return p


def run_evaluate(args) -> int:
    import dataclasses

    from services.evaluation import evaluate
    suite = evaluate.SUITES[args.suite]
    if not args.budget_s > 0:
        return _error("evaluate", f"--budget-s must be > 0, got {args.budget_s}", EXIT_BAD_INPUT)
    known = {c.scene for c in suite.cases}
    unknown = sorted(set(args.scene or ()) - known)
    if unknown:
        return _error("evaluate", f"scene {unknown[0]!r} is not in suite {suite.name!r} "
                                  f"(known: {', '.join(sorted(known))})", EXIT_BAD_INPUT)
    suite = dataclasses.replace(suite, reference_spp_scale=args.reference_spp_scale)
    ev = evaluate.evaluate(suite, args.budget_s, args.method, args.scene, args.reference_cache,
                           args.seed, log=lambda line: print(line, file=sys.stderr), out_dir=args.out)
    for path in evaluate.write_results(ev, args.out):
        print(path)
    print(evaluate.summary_markdown(ev))
    return EXIT_FAILED if ev.failed else EXIT_OK
