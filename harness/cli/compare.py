"""`dosppm compare`: error metrics of one image against a reference.

    dosppm compare A.exr B.exr [--diff diff.png] [--json]

Exit codes: 0 success, 2 bad input (an unreadable image, mismatched sizes,
NaN pixels); each error is one line on stderr that names the file.
"""
from __future__ import annotations

import json

import numpy as np

from dosppm_core.film import FilmError, read_exr
from harness import metrics
from services.cli.errors import EXIT_OK, fail


def add_parser(sub) -> None:
    p = sub.add_parser(
        "compare", help="error metrics of one EXR against a reference EXR",
        description="Print RMSE, relMSE and mean-luminance bias of A against the "
                    "reference B, one `name value` per line.")
    p.add_argument("a", help="the image to judge (EXR)")
    p.add_argument("b", help="the reference (EXR)")
    p.add_argument("--diff", help="write a false-colour relative-difference PNG here")
    p.add_argument("--json", action="store_true",
                   help="print one JSON object instead of `name value` lines")
    p.set_defaults(func=run)


def run(args) -> int:
    images = []
    for path in (args.a, args.b):
        try:
            rgb = read_exr(path)[0]
        except FilmError as exc:
            return fail(str(exc))
        bad = int(np.sum(~np.isfinite(rgb)))
        if bad:
            return fail(f"{path}: contains NaN or Inf ({bad} values)")
        images.append(rgb)
    a, b = images
    if a.shape != b.shape:
        return fail(f"{args.a}: size {a.shape[1]}x{a.shape[0]} differs from {args.b}: {b.shape[1]}x{b.shape[0]}")
    try:
        result = _metrics(a, b)
        if args.diff:
            result["diff_scale"] = metrics.difference_png(args.diff, a, b)
    except (ValueError, FilmError) as exc:
        return fail(str(exc))
    _print_metrics(result, args)
    return EXIT_OK


def _metrics(a: np.ndarray, b: np.ndarray) -> dict:
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
