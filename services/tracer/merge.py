"""Accounting-only results merged into one message to the server (issue 32:
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
latest; an eye iteration's hit points made add (none are kept: results
with hit points, deposits or eye light are never merged), and results of
different eye iterations (or of photons) go in different messages.
"""
from __future__ import annotations

import numpy as np

from dosppm_core.jobs import HitPoints
from services.credit import Account, by_job

HOLD_S = 0.1           # the first merged results wait at most this long (a job completes this much later)
MAX_TERMS = 1 << 16    # credit terms held for one merged send, at most


def mergeable(fields: dict) -> bool:
    """Results that are accounting only: photon steps and emissions whose
    deposits stay at the tracer, eye and shadow steps whose light it holds
    and whose hit points are not kept (`hit_point_stride`)."""
    hits = fields.get("hits")
    return fields.get("deposits") is None and fields.get("emitted_pixels") is None and \
        (hits is None or len(hits) == 0)


class MergedResults:
    """Mergeable results held until due, one merged message per eye
    iteration they belong to (None: photons)."""

    def __init__(self, hold_s: float = HOLD_S):
        self.hold_s = hold_s
        self.clear()

    def add(self, fields: dict, now: float) -> None:
        if not self.parts:
            self.since = now
        self.latest = fields
        self.parts.setdefault(fields.get("eye_iteration"), []).append(fields)
        self.terms += len(fields["credit_job"])

    def due(self, now: float) -> bool:
        return bool(self.parts) and (now - self.since >= self.hold_s or self.terms >= MAX_TERMS)

    def take(self) -> list[dict]:
        """The merged results' fields, photons' first; holds nothing after."""
        parts, latest = self.parts, self.latest
        self.clear()
        out = [p[0] if len(p) == 1 else merged(p) for _key, p in sorted(parts.items(), key=_photons_first)]
        for f in out:       # the queue as it is now, whichever message the server reads last
            f["queued"], f["queue_target"] = latest["queued"], latest["queue_target"]
        return out

    def clear(self) -> None:
        self.parts, self.since, self.terms, self.latest = {}, None, 0, None


def _photons_first(item) -> tuple:
    return (item[0] is not None, item[0] or 0)


def merged(parts: list[dict]) -> dict:
    """One results message's fields for `parts` (each `mergeable`, all of
    one eye iteration or none)."""
    last = parts[-1]
    ids = np.concatenate([p["job_ids"] for p in parts])
    jobs, at = np.unique(ids, return_inverse=True)
    fed, left = np.zeros(len(jobs), np.int64), np.zeros(len(jobs), np.int64)
    np.add.at(fed, at, np.concatenate([p["job_fed"] for p in parts]))
    np.add.at(left, at, np.concatenate([p["job_left"] for p in parts]))
    chunks = {p["chunk"] for p in parts}
    out = dict(chunk=chunks.pop() if len(chunks) == 1 else None,
               ends=np.sum([p["ends"] for p in parts], axis=0, dtype=np.int64),
               culled=sum(int(p.get("culled", 0)) for p in parts), job_ids=jobs.astype(np.int64),
               job_fed=fed, job_left=left,
               **summed_credit(np.concatenate([p["credit_job"] for p in parts]),
                               np.concatenate([p["credit_exp"] for p in parts])),
               queued=last["queued"], queue_target=last["queue_target"])
    if last.get("eye_iteration") is not None:
        out.update(eye_iteration=last["eye_iteration"], hits=HitPoints.empty(),
                   hit_points_made=sum(int(p.get("hit_points_made", 0)) for p in parts))
    return out


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
