"""Figures the reliability tests measure (detection times, slowdowns, peak
server RSS, the largest outbox, rejoins), kept as an artifact (issue 15).

`record(test, **values)` notes what a test measured; `outcome(test, flag)`
wraps a test's body so that it records `flag`=1 when the body passes and 0
when it fails (a failed run counts, issue 34), with the values measured
before the failure. With
DOSPPM_RECORD_FIGURES=PATH set, the session's figures are merged into the
JSON file at PATH when it ends, each test's under its own name with every
sample kept (added to those of earlier runs of the same commit), plus the
provenance of the run; `benchmarks/tables.py` makes
docs/reliability.md's table from `benchmarks/results/reliability.json`.
Without it nothing is written (a plain test run leaves the tree alone).
"""
from __future__ import annotations

import contextlib
import json
import os

import pytest

ENV = "DOSPPM_RECORD_FIGURES"
DIRTY_ENV = "DOSPPM_FIGURES_DIRTY"    # benchmarks/reliability.sh --dirty: recorded in the file
_FIGURES: dict[str, dict[str, list]] = {}


def record(test: str, **values) -> None:
    for k, v in values.items():
        _FIGURES.setdefault(test, {}).setdefault(k, []).append(v)


@contextlib.contextmanager
def outcome(test: str, flag: str, **values):
    """Record `flag`=1 for `test` if the block ends normally, 0 if it
    raises (a failed assertion or an error), together with `values` and
    whatever the block adds to the dict it yields: measured values only
    when measured. A skip or an interrupt records nothing."""
    measured = dict(values)
    try:
        yield measured
    except (pytest.skip.Exception, KeyboardInterrupt):
        raise
    except BaseException:
        record(test, **{flag: 0}, **measured)
        raise
    record(test, **{flag: 1}, **measured)


def write_if_asked() -> str | None:
    """Merge this session's figures into $DOSPPM_RECORD_FIGURES; its path, or None."""
    path = os.environ.get(ENV)
    if not path or not _FIGURES:
        return None
    from harness.provenance import provenance, write_results
    try:
        with open(path, encoding="utf-8") as f:
            old = json.load(f)
    except (OSError, ValueError):
        old = {}
    tests = dict(old.get("tests", {}))
    runs = dict(old.get("runs", {}))
    here = provenance()
    for test, values in _FIGURES.items():
        # Runs of the same commit add samples (a test run N times gives
        # "successes of N"); a new commit starts over.
        if runs.get(test, {}).get("commit") == here["commit"]:
            # Every key of either (a failed run may not have measured them all).
            was = tests[test]
            values = {k: list(was.get(k, [])) + values.get(k, []) for k in dict.fromkeys([*was, *values])}
        tests[test] = values
        runs[test] = {"commit": here["commit"], "date": here["date"]}
    extra = {"dirty_allowed": True} if os.environ.get(DIRTY_ENV) == "1" or old.get("dirty_allowed") else {}
    write_results(path, {"tests": tests, "runs": runs, **extra})
    return path
