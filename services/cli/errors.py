"""How every subcommand reports: a user's mistake or a failure is one line
on stderr (`dosppm: error: ...`) and a non-zero exit status, never a
traceback.

Exit statuses: 0 success, 1 the work failed (a reference renderer missing,
a tracer lost), 2 bad input (an unreadable scene, image or setting), 130
interrupted."""
from __future__ import annotations

import argparse
import contextlib
import sys
import warnings

EXIT_OK, EXIT_FAILED, EXIT_BAD_INPUT, EXIT_INTERRUPTED = 0, 1, 2, 130


class Parser(argparse.ArgumentParser):
    """argparse, but a mistake is one line naming the flag and value (not
    the whole usage), with exit status 2; subcommands inherit it. Here, not
    in main.py, so that the harness's verbs (harness/cli/) parse alike
    without importing the command that loads them."""

    def error(self, message: str):
        self.exit(2, f"{self.prog}: error: {message} (see {self.prog} --help)\n")


def fail(message: str, code: int = EXIT_BAD_INPUT) -> int:
    """Print `dosppm: error: MESSAGE` and return `code` for the caller to exit with."""
    print(f"dosppm: error: {message}", file=sys.stderr)
    return code


def warn(message) -> None:
    print(f"dosppm: warning: {message}", file=sys.stderr)


@contextlib.contextmanager
def warnings_as_lines():
    """The library's warnings raised inside (say, a scene feature it
    approximates) printed as one `dosppm: warning:` line each afterwards."""
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        yield
    for w in caught:
        warn(w.message)
