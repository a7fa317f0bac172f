"""Where a benchmark figure came from: every results file under
`benchmarks/results/` carries the commit it measured, the date, the
machine and the command, so that a reader can re-run it and compare
(issue 13). Every benchmark writes its JSON through `write_results`.
"""
from __future__ import annotations

import datetime
import json
import os
import platform
import shlex
import statistics
import subprocess
import sys

# The repository's top (harness/ is one below it): a change
# anywhere in it, dosppm_core/ and benchmarks/ included, makes a figure dirty.
ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def commit() -> str:
    """HEAD's hash, with '+dirty' when the tree differs from it anywhere:
    an edit, staged or not, or a new file git does not ignore (a module not
    yet added is code no commit holds as much as an edited one). Results
    files do not count: one script regenerating several writes each in
    turn."""
    def git(*args):
        return subprocess.run(["git", *args], cwd=ROOT, capture_output=True, text=True).stdout.strip()
    head = git("rev-parse", "HEAD") or "unknown"
    changed = git("status", "--porcelain", "--untracked-files=normal", "--", ".", ":(exclude)benchmarks/results")
    return head + ("+dirty" if changed else "")


def machine() -> dict:
    """The facts that change a throughput figure: CPU model and count,
    memory, OS, and the versions of the libraries in the hot loops."""
    out = {"cpu_count": os.cpu_count(), "platform": platform.platform(),
           "python": platform.python_version(), "cpu": _cpu_model(), "memory_gib": _memory_gib()}
    for name in ("numpy", "numba", "embreex", "zmq"):
        try:
            out[name] = __import__(name).__version__
        except (ImportError, AttributeError):
            out[name] = None
    return out


def _cpu_model() -> str:
    try:
        with open("/proc/cpuinfo", encoding="utf-8") as f:
            for line in f:
                if line.startswith("model name"):
                    return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def _memory_gib() -> float | None:
    try:
        return round(os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES") / 2 ** 30, 1)
    except (ValueError, OSError, AttributeError):
        return None


def provenance(argv: list[str] | None = None) -> dict:
    argv = sys.argv if argv is None else argv
    return {"commit": commit(),
            "date": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
            "machine": machine(),
            "command": " ".join(shlex.quote(a) for a in [_short(argv[0]), *argv[1:]])}


def _short(program: str) -> str:
    """A program under the checkout by its path from the top (as the
    README writes commands), anything else as given."""
    if os.path.isabs(program) and program.startswith(ROOT + os.sep):
        return os.path.relpath(program, ROOT)
    return os.path.basename(program) if os.path.isabs(program) else program


def median_of(samples: list[dict]) -> dict:
    """The per-key median of several runs' numeric fields (other fields
    from the first run), with every run kept under 'samples'."""
    out = dict(samples[0])
    for k, v in samples[0].items():
        if isinstance(v, (int, float)) and not isinstance(v, bool):
            out[k] = statistics.median(s[k] for s in samples)
    out["repeats"] = len(samples)
    out["samples"] = samples
    return out


def write_results(path: str, payload: dict, argv: list[str] | None = None) -> None:
    """`payload` with its provenance, as indented JSON at `path`."""
    os.makedirs(os.path.dirname(os.path.abspath(path)), exist_ok=True)
    with open(path, "w", encoding="utf-8") as f:
        json.dump({"provenance": provenance(argv), **payload}, f, indent=1)
        f.write("\n")
