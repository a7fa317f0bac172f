"""A render's time limit as a deadline (issue 29), for every mode.

`--time T` promises the image within `grace_s(T)` = max(2 s, 5% of T)
after T. A renderer meets it by not starting work it cannot finish: it
sizes what it emits near the end by its measured rate, so what is in
flight at T is small, and it is either applied within the grace or
left out and counted: whole jobs in the render service, the rays still
queued in OSPPM (their photons' deposits so far stay applied: see
modes/osppm.py). The clock is the render's: it
starts with the first iteration (compiling kernels and loading the scene
come before it).
"""
from __future__ import annotations

import time
from dataclasses import dataclass

GRACE_MIN_S = 2.0
GRACE_SHARE = 0.05


def grace_s(seconds: float) -> float:
    """How long after a time limit of `seconds` the image may come."""
    return max(GRACE_MIN_S, GRACE_SHARE * float(seconds))


@dataclass(frozen=True)
class Deadline:
    at: float             # time.perf_counter() when the limit falls
    grace: float          # seconds past `at` the image may come

    @classmethod
    def after(cls, seconds: float, start: float | None = None) -> Deadline:
        start = time.perf_counter() if start is None else start
        return cls(start + float(seconds), grace_s(seconds))

    def left(self) -> float:
        """Seconds until the limit (negative once past it)."""
        return self.at - time.perf_counter()

    @property
    def passed(self) -> bool:
        return self.left() <= 0

    def hard_left(self) -> float:
        """Seconds until the image must be in hand."""
        return self.left() + self.grace


def that_fit(seconds_left: float | None, wanted: int, per_s: float | None, unit: int = 1) -> int:
    """How many of `wanted` items (photons) to start now so they are done
    within `seconds_left` at `per_s` (either None: no deadline, or not
    measured yet: start them all): whole `unit`s (jobs), at least one while
    time is left, none after."""
    if seconds_left is None or per_s is None or per_s <= 0:
        return wanted
    if seconds_left <= 0:
        return 0
    fit = int(per_s * seconds_left) // unit * unit
    return min(wanted, max(unit, fit))


class Rate:
    """Items per second over recent work (an exponential mean, so a rate
    that changes as the hit points shrink is followed)."""

    def __init__(self, weight: float = 0.5):
        self.weight, self.per_s = weight, None

    def add(self, items: int, seconds: float) -> None:
        if items <= 0 or seconds <= 0:
            return
        r = items / seconds
        self.per_s = r if self.per_s is None else (1 - self.weight) * self.per_s + self.weight * r
