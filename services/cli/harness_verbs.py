"""The harness's verbs on the `dosppm` command: bench, reference, compare
and evaluate. Each is a door: its parser, flags and work live in
harness/cli/, which this module imports only when one of them runs, so that
`dosppm render`, `server` and `worker` never load the harness (nor
Mitsuba, matplotlib or pbrt's glue). tests/test_layout.py allows this
module, and no other in services/ or dosppm_core/, to import harness, and
only inside a function.

    dosppm evaluate failure-modes --budget-s 8   is   python -m harness evaluate failure-modes --budget-s 8
"""
from __future__ import annotations

import argparse
from dataclasses import dataclass

from services.cli.errors import EXIT_FAILED, fail


@dataclass(frozen=True)
class HarnessVerb:
    name: str
    help: str

    def add_parser(self, sub) -> None:
        # Every word after the verb, flags and --help included, goes to the
        # harness's own parser: no prefix character is a flag here.
        p = sub.add_parser(self.name, help=self.help, add_help=False, prefix_chars="\0")
        p.add_argument("words", nargs=argparse.REMAINDER)
        p.set_defaults(func=self.run)

    def run(self, args) -> int:
        try:
            from harness.cli.main import main
        except ImportError as e:      # an install without the harness (the Docker image)
            if not (e.name or "").startswith("harness"):
                raise
            return fail(f"{self.name}: the evaluation harness (harness/) is not installed here; "
                        "install dosppm from its repository", EXIT_FAILED)
        return main([self.name, *args.words])


# In the order `dosppm --help` lists them; each help line is the harness's own.
VERBS = (
    HarnessVerb("bench", "measure tracing and statistics-update throughput"),
    HarnessVerb("reference", "render a reference image with Mitsuba 3"),
    HarnessVerb("compare", "error metrics of one EXR against a reference EXR"),
    HarnessVerb("evaluate", "speed against accuracy: every method on a suite of scenes"),
)
