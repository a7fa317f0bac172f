"""Progress reporting for long renders: a one-line bar on a terminal and a
machine-readable JSON-lines log."""
from __future__ import annotations

import glob
import json
import os
import sys
import time

from dosppm_core.kernels import paths

COMPILING = "compiling kernels (first run on this machine; cached afterwards, a minute or two)..."


def human(n: float) -> str:
    for unit, div in (("G", 1e9), ("M", 1e6), ("k", 1e3)):
        if abs(n) >= div:
            return f"{n / div:.2f}{unit}"
    return f"{n:.0f}"


def stderr_lines(quiet: bool):
    """A function printing its arguments as a line on stderr (nothing when `quiet`)."""
    if quiet:
        return lambda *parts: None
    return lambda *parts: print(*parts, file=sys.stderr)


class ProgressReporter:
    """Feeds on `Progress` records (dosppm_core.settings). `limit` is (kind,
    value) with kind one of 'seconds', 'photons', 'iterations', for the ETA."""

    def __init__(self, limit: tuple[str, float], log_path: str | None = None,
                 stream=None, quiet: bool = False):
        self.limit = limit
        self.stream = stream or sys.stderr
        self.quiet = quiet
        self.tty = hasattr(self.stream, "isatty") and self.stream.isatty()
        self.log = open(log_path, "a", encoding="utf-8") if log_path else None
        self.t0 = time.perf_counter()
        self._last_print = 0.0

    def __call__(self, p) -> None:
        wall = time.perf_counter() - self.t0
        rate = p.photons_emitted / p.seconds if p.seconds > 0 else 0.0
        record = {"iteration": p.iteration, "photons": p.photons_emitted,
                  "hit_points": p.hit_points, "seconds": round(p.seconds, 4),
                  "wall_seconds": round(wall, 4), "photons_per_s": round(rate, 1),
                  # When the render's clock started (what --time counts from), as a Unix time.
                  "started_unix": round(time.time() - p.seconds, 3),
                  "path_ends": p.path_ends}
        if self.log:
            self.log.write(json.dumps(record) + "\n")
            self.log.flush()
        if self.quiet:
            return
        if self.tty or wall - self._last_print > 5.0 or p.iteration == 1:
            self._last_print = wall
            line = (f"iteration {p.iteration}  photons {human(p.photons_emitted)}  "
                    f"{human(rate)} photons/s  ETA {self._eta(p, rate):.0f} s")
            end = "\r" if self.tty else "\n"
            self.stream.write(line.ljust(72) + end)
            self.stream.flush()

    def _eta(self, p, rate: float) -> float:
        kind, value = self.limit
        if kind == "seconds":
            return max(0.0, value - p.seconds)
        if kind == "photons":
            return max(0.0, (value - p.photons_emitted) / rate) if rate > 0 else float("inf")
        per_iter = p.seconds / max(p.iteration, 1)
        return max(0.0, (value - p.iteration) * per_iter)

    def close(self) -> None:
        if self.tty and not self.quiet:
            self.stream.write("\n")
        if self.log:
            self.log.close()
            self.log = None


def kernels_cached() -> bool:
    """Whether numba's on-disk cache already holds the main kernel, so the
    first render of a fresh install can say it is compiling."""
    try:
        folder = paths.scatter_photons._cache._cache_path   # in-tree or numba's user-wide cache
    except Exception:  # private numba API: never let it break a render
        return True
    return bool(glob.glob(os.path.join(glob.escape(folder), "paths.scatter_photons-*.nbi")))
