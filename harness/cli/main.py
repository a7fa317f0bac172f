"""The harness's verbs: `dosppm bench`, `reference`, `compare` and
`evaluate` (services/cli/harness_verbs.py hands them their words), or the
same without the render service's command:

    python -m harness evaluate failure-modes --budget-s 8
"""
from __future__ import annotations

import argparse

from harness.cli import bench, compare, evaluate, reference
from services.cli.errors import Parser

# Each verb's module: `add_parser(sub)` registers it, with its `run`.
VERBS = (bench, reference, compare, evaluate)


def build_parser() -> Parser:
    # prog "dosppm": a verb's usage and one-line errors read as the
    # command the user typed ("dosppm evaluate: error: ...").
    parser = Parser(prog="dosppm", description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = parser.add_subparsers(dest="command", required=True)
    for verb in VERBS:
        verb.add_parser(sub)
    return parser


def main(argv: list[str]) -> int:
    """Run one verb: `argv` is the verb and its words."""
    args = build_parser().parse_args(argv)
    return args.func(args)
