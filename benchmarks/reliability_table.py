"""The reliability tables (docs/reliability.md, the README) from
benchmarks/results/reliability.json, which tests/helpers/figures.py fills:
per fault test, every run's success flag (1 or 0, a failed run included)
and the values it measured, and the commit the runs were made at (issue 34).

Each row says "k of n runs" for its flag, quotes a measured value as the
median (range) over the runs that measured it, names the tracer timeout it
ran at, and says so visibly when it rests on fewer than FEW runs.
"""
from __future__ import annotations

import statistics

FLAGS = ("evicted", "rejoined", "resumed", "passed")   # 1 per run that passed, 0 per run that failed
FEW = 5                                                 # fewer runs than this is a thin figure
NOT_MEASURED = ("timeout_s",)                           # a setting, shown in its own column


def flag_of(values: dict) -> str | None:
    return next((k for k in FLAGS if k in values), None)


def runs_of(values: dict) -> int:
    """How many runs a test's figures come from: its flag's count, or
    (figures recorded before failures were) the most samples of any value."""
    flag = flag_of(values)
    return len(values[flag]) if flag else max((len(v) for v in values.values()), default=0)


def few(n: int, brief: bool = False) -> str:
    if n >= FEW:
        return ""
    return f" (< {FEW} runs)" if brief else f" (n={n}, fewer than {FEW})"


def k_of_n(values: dict, brief: bool = False) -> str:
    """'evicted in 4 of 5 runs' (`brief`: '4 of 5'), with the thin-figure
    note when n < FEW; a test recorded before its flag was has '?' for k."""
    flag = flag_of(values)
    n = runs_of(values)
    if brief:
        return f"{sum(values[flag]) if flag else '?'} of {n}{few(n, brief)}"
    if flag is None:
        return f"success not recorded in {n} run{'s' if n > 1 else ''}{few(n)}"
    return f"{flag} in {sum(values[flag])} of {n} runs{few(n)}"


def number(x) -> str:
    if isinstance(x, float) and not x.is_integer():
        return f"{x:,.0f}" if abs(x) >= 1000 else f"{x:.4g}"
    return f"{int(x):,}"


def spread(xs: list, n: int | None = None) -> str:
    """The median (range) of a value's samples, and how many of the `n`
    runs measured it when fewer did."""
    med = statistics.median(xs)
    lo, hi = min(xs), max(xs)
    out = number(med) if lo == hi else f"{number(med)} ({number(lo)}-{number(hi)})"
    return out + (f" [{len(xs)} of {n} runs measured]" if n is not None and len(xs) < n else "")


def timeout(values: dict) -> str:
    ts = sorted(set(values.get("timeout_s", [])))
    return ", ".join(f"{number(float(t))} s" for t in ts) if ts else "?"


def short_commit(commit: str, width: int = 10) -> str:
    return commit[:width] + ("+dirty" if commit.endswith("+dirty") else "")


def commits(doc: dict, width: int = 10) -> str:
    """The commit(s) the rows were measured at, from each test's "runs"
    record, not the file's top provenance (the last pytest run to write it)."""
    runs = doc.get("runs", {})
    seen: dict[str, int] = {}
    for test in doc["tests"]:
        c = runs.get(test, {}).get("commit", "unknown")
        seen[c] = seen.get(c, 0) + 1
    if len(seen) == 1:
        text = f"commit {short_commit(next(iter(seen)), width)}"
    else:
        text = ("rows from different commits: " if width >= 10 else "mixed commits: ") + ", ".join(
            f"{short_commit(c, width)} ({k} row{'s' if k > 1 else ''})" for c, k in seen.items())
    return text + (" (run with --dirty)" if doc.get("dirty_allowed") else "")


def full(doc: dict) -> str:
    """Every test's flag, measured values and timeout, one row each."""
    lines = ["| fault or load | runs | measured: median (range) | tracer timeout | run at |",
             "|---|---|---|---|---|"]
    for test, values in doc["tests"].items():
        n, flag = runs_of(values), flag_of(values)
        measured = "; ".join(f"{k.replace('_', ' ')} {spread(v, n)}" for k, v in values.items()
                             if k != flag and k not in NOT_MEASURED and v)
        run = doc.get("runs", {}).get(test, {})
        at = timeout(values) if values.get("timeout_s") else "not recorded"
        lines.append(f"| {test} | {k_of_n(values)} | {measured or '-'} | {at} "
                     f"| {short_commit(run.get('commit', '?'))}, {run.get('date', '?')[:10]} |")
    return "\n".join(lines)


def _ratio(v: dict) -> str:
    pairs = [s / h for s, h in zip(v["seconds"], v["healthy_seconds"])]
    return f"{spread([round(p, 2) for p in pairs])}x healthy time"


# The README's cut: a short label, and what happened, per test (by the
# start of its name in the results file).
SHORT = [
    ("tracer killed", "tracer SIGKILL", lambda v: f"evicted after {spread(v['detected_s'])} s"),
    ("tracer hung (SIGSTOP), then woken", "tracer SIGSTOP, woken", lambda v: "-"),
    ("server killed (SIGKILL), --resume", "server SIGKILL, --resume", lambda v: "-"),
    ("cable cut 2 s (< timeout)", "cable cut 2 s",
     lambda v: f"completions stall to {spread([round(100 * r) for r in v['rate_during_cut']])}%"),
    ("cable cut 8 s, then back", "cable cut 8 s, then back", lambda v: "-"),
    ("5% packet loss on a tracer host", "5% packet loss", _ratio),
    ("16 tracers, 1k jobs in flight, one stopped 8 s", "16 tracers, one stopped 8 s",
     lambda v: f"server peak {spread(v['server_peak_rss_mib'])} MiB"),
]


def short(doc: dict) -> str:
    t = doc["tests"]
    lines = ["| fault or load | timeout | passed | median (range) |", "|---|---|---|---|"]
    for name, label, say in SHORT:
        key = next((k for k in t if k.startswith(name)), None)
        if key is None:
            continue
        try:
            said = say(t[key])
        except (KeyError, ValueError):          # every run failed before measuring it
            said = "not measured"
        lines.append(f"| {label} | {timeout(t[key])} | {k_of_n(t[key], brief=True)} | {said} |")
    return "\n".join(lines)
