"""Test helper: credit (services/credit.py) summed exactly, per job."""
from __future__ import annotations

from fractions import Fraction

import numpy as np


def credit_sum(terms) -> dict[int, Fraction]:
    """{job: its credit} over `terms`, (job ids, exponents) pairs of arrays;
    a term is 2^-exponent of its job, summed as fractions (no rounding)."""
    out: dict[int, Fraction] = {}
    for job, exp in terms:
        for j, e in zip(np.asarray(job).tolist(), np.asarray(exp).tolist()):
            out[j] = out.get(j, Fraction(0)) + Fraction(1, 1 << e)
    return out
