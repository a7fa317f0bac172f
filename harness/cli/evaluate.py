"""`dosppm evaluate`: speed against accuracy, every method on a suite of
scenes (the evaluation is `harness.evaluate`).

    dosppm evaluate SUITE [--budget-s S] [--out DIR] [--method M ...] [--scene NAME ...]
                          [--shared DIR]

Peers that are not installed (Mitsuba 3, pbrt-v4) and cases whose files
are not in the shared folder are skipped, each with its reason.

Exit codes: 0 success, 1 a method failed on a scene (recorded in the
results), 2 bad input.
"""
from __future__ import annotations

import dataclasses
import sys

from harness import evaluate, suites
from services import config
from services.cli.errors import EXIT_FAILED, EXIT_OK, fail


def add_parser(sub) -> None:
    p = sub.add_parser(
        "evaluate", help="speed against accuracy: every method on a suite of scenes",
        description="Render each scene of SUITE with each method, stopped at 1/8, 1/4, 1/2 "
                    "and all of the time budget, and score every stop against the scene's "
                    "reference: Mitsuba 3's (rendered once, then cached), or an image in the "
                    "shared folder (pbrt-v4's, for sponza-point). Writes results.json, "
                    "results.csv, summary.md and, with matplotlib, the charts.")
    p.add_argument("suite", choices=sorted(evaluate.SUITES), help="the suite of scenes")
    p.add_argument("--budget-s", type=config.positive_float, default=20.0,
                   help="render seconds per method and scene (default 20)")
    p.add_argument("--out", default="evaluation", help="output folder (default ./evaluation)")
    p.add_argument("--method", action="append", choices=sorted(evaluate.METHODS),
                   help="only this method (repeatable; default: the suite's)")
    p.add_argument("--scene", action="append", help="only this scene of the suite (repeatable)")
    p.add_argument("--reference-cache", help="where references are kept "
                                             "(default ~/.cache/dosppm/references)")
    p.add_argument("--reference-spp-scale", type=config.positive_float, default=1.0,
                   help="scale the suite's reference sample counts (quick looks: 0.1)")
    p.add_argument("--shared", metavar="DIR",
                   help=f"the shared folder of scenes and references (default ${suites.SHARED_ENV}); "
                        "cases that need it are skipped without it")
    p.add_argument("--seed", type=config.non_negative_int, default=1)
    p.set_defaults(func=run)


def run(args) -> int:
    suite = evaluate.SUITES[args.suite]
    if not args.budget_s > 0:
        return fail(f"--budget-s must be > 0, got {args.budget_s}")
    known = {c.scene for c in suite.cases}
    unknown = sorted(set(args.scene or ()) - known)
    if unknown:
        return fail(f"scene {unknown[0]!r} is not in suite {suite.name!r} (known: {', '.join(sorted(known))})")
    suite = dataclasses.replace(suite, reference_spp_scale=args.reference_spp_scale)
    ev = evaluate.evaluate(suite, args.budget_s, args.method, args.scene, args.reference_cache,
                           args.seed, log=lambda line: print(line, file=sys.stderr), out_dir=args.out,
                           shared=args.shared)
    for path in evaluate.write_results(ev, args.out):
        print(path)
    print(evaluate.summary_markdown(ev))
    return EXIT_FAILED if ev.failed else EXIT_OK
