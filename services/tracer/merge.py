"""Photon-only results merged into one message to the server (issue 32:
the server's CPU per photon).

Gathering at the tracers, most `results` messages carry only accounting:
paths ended per job, the credit they return, how the paths ended, the
queue. Each costs the server a decode and its bookkeeping whatever its
size, so consecutive ones are merged and sent as one, at most
HOLD_S after the first, and at once when the tracer runs out of work or
has something else for the server (in order).

Merging changes nothing the server computes: ends and culled add; each
job's fed and left add (only fed - left is read, the paths ended); credit
terms are added per job, exactly, and sent as the fewest terms 2**-e
that sum to the same (a job completes when its terms sum to 1, however
they are cut: services/credit.py); queued and queue_target are the
latest. Results with deposits, hit points or eye light are never merged
(they are not accounting only).
"""
from __future__ import annotations

import numpy as np

from services.credit import Account, by_job

HOLD_S = 0.05          # the first merged results wait at most this long (a job completes this much later)
MAX_TERMS = 1 << 16    # credit terms in one merged message, at most


def mergeable(fields: dict) -> bool:
    """Results that are accounting only (photon steps and emissions when
    the deposits stay at the tracer)."""
    return all(fields.get(k) is None for k in ("deposits", "hits", "emitted_pixels", "eye_iteration"))


class MergedResults:
    def __init__(self, hold_s: float = HOLD_S):
        self.hold_s = hold_s
        self.parts: list[dict] = []
        self.since: float | None = None
        self.terms = 0

    def add(self, fields: dict, now: float) -> None:
        if not self.parts:
            self.since = now
        self.parts.append(fields)
        self.terms += len(fields["credit_job"])

    def due(self, now: float) -> bool:
        return bool(self.parts) and (now - self.since >= self.hold_s or self.terms >= MAX_TERMS)

    def take(self) -> dict | None:
        """The merged fields (None: nothing held); holds nothing after."""
        parts, self.parts, self.since, self.terms = self.parts, [], None, 0
        if len(parts) <= 1:
            return parts[0] if parts else None
        return merged(parts)

    def clear(self) -> None:
        self.parts, self.since, self.terms = [], None, 0


def merged(parts: list[dict]) -> dict:
    """One results message's fields for `parts` (each `mergeable`)."""
    last = parts[-1]
    ids = np.concatenate([p["job_ids"] for p in parts])
    fed = np.concatenate([p["job_fed"] for p in parts])
    left = np.concatenate([p["job_left"] for p in parts])
    jobs, at = np.unique(ids, return_inverse=True)
    sum_fed, sum_left = np.zeros(len(jobs), np.int64), np.zeros(len(jobs), np.int64)
    np.add.at(sum_fed, at, fed)
    np.add.at(sum_left, at, left)
    chunks = {p["chunk"] for p in parts}
    return dict(chunk=chunks.pop() if len(chunks) == 1 else None,
                ends=np.sum([p["ends"] for p in parts], axis=0, dtype=np.int64),
                culled=sum(int(p.get("culled", 0)) for p in parts),
                job_ids=jobs.astype(np.int64), job_fed=sum_fed, job_left=sum_left,
                **summed_credit(np.concatenate([p["credit_job"] for p in parts]),
                                np.concatenate([p["credit_exp"] for p in parts])),
                queued=last["queued"], queue_target=last["queue_target"])


def summed_credit(job: np.ndarray, exp: np.ndarray) -> dict:
    """Credit terms (job, 2**-exp) added per job, exactly, as the fewest
    terms with the same sums: one term for a job whose returned credit is
    a power of two (a whole job's: exponent 0), by job id."""
    jobs, exps = [], []
    for j, e in sorted(by_job(job, exp).items()):
        acc = Account()
        acc.add(e)
        num = acc.num
        for i in range(num.bit_length()):
            if num >> i & 1:
                jobs.append(j)
                exps.append(acc.exp - i)
    return {"credit_job": np.array(jobs, np.int64), "credit_exp": np.array(exps, np.int64)}
