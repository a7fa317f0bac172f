"""Credit: how the server knows that a job has finished *and* that
everything it produced is in hand (weight throwing, Mattern 1989).

Counting ended paths is not enough. A tracer step whose paths all leave
its chunk ends none of them, yet its `results` message carries the
deposits made on the way; the tracer downstream can end those paths and
report before that message reaches the server (two tracers' messages
arrive in no guaranteed order), and the job would be complete with
deposits still on their way (issue 15).

So every package of a job's rays carries a share of the job's credit, and
every `results` message returns some:
- the server gives each job credit 1 and splits it among the packages
  it sends (parts starting in different chunks);
- a tracer that traces a batch splits the credit its packages brought
  between the packages leaving the step and the server, always keeping a
  positive share for the server, in the same `results` message as the
  step's deposits and hit points;
- a job is complete when the returned credit sums to exactly 1.
Then no package of the job exists anywhere, and no results message with
its deposits is still on its way: each one returned credit the sum needs.

Credit is held as terms 2**-e (e >= 0 an integer exponent): the server
sums them exactly with Python integers, and a split never rounds. Lost
messages lose credit, so their jobs never complete: the server's watchdog
re-emits them (services/server/state.py), as it does for lost paths.
"""
from __future__ import annotations

import numpy as np

# A split adds log2(packages + 1) bits, so a job's exponents grow with the
# steps along its longest chain of portal crossings (a few hundred bits at
# most); the wire refuses more, which bounds the server's integers.
MAX_EXP = 1 << 14


def _bits(m: np.ndarray) -> np.ndarray:
    """b with 2**b > m >= 0: room for m outgoing shares and one returned."""
    return np.array([int(x).bit_length() for x in m.tolist()], np.int64)


def split(job: np.ndarray, exp: np.ndarray, outgoing: list[np.ndarray]):
    """Divide the credit terms (job, exp) of a traced batch.

    `outgoing` holds the job column of each package leaving the step. Each
    gets one term per job it carries; the rest of every job's credit is
    returned. Returns ((returned job, returned exp), [(job, exp)] in the
    order of `outgoing`)."""
    job, exp = np.asarray(job, np.int64), np.asarray(exp, np.int64)
    ids = [np.unique(o) for o in outgoing]
    order = np.lexsort((exp, job))
    job, exp = job[order], exp[order]
    head = np.r_[True, job[1:] != job[:-1]] if len(job) else np.zeros(0, bool)
    hj, he = job[head], exp[head]                       # each job's largest term
    m = np.zeros(len(hj), np.int64)
    if ids and sum(map(len, ids)):
        out_ids, counts = np.unique(np.concatenate(ids), return_counts=True)
        at = np.minimum(np.searchsorted(hj, out_ids), max(len(hj) - 1, 0))
        if not len(hj) or np.any(hj[at] != out_ids):
            raise ValueError("rays left for a job that brought no credit")
        m[at] = counts
    b = _bits(m)
    new = he + b                                        # each outgoing share: 2**-(e + b)
    if len(new) and new.max(initial=0) > MAX_EXP:
        raise ValueError(f"credit exponent {int(new.max())} passes {MAX_EXP}")
    # Returned: the other terms, the heads of jobs with nothing leaving, and
    # the remainder (2**b - m) * 2**-(e + b) >= 2**-(e + b), bit by bit.
    r_job, r_exp = [job[~head], hj[m == 0]], [exp[~head], he[m == 0]]
    rem = (np.left_shift(1, b) - m)[m > 0]
    for i in range(int(b.max(initial=0))):
        bit = (rem >> i) & 1 == 1
        r_job.append(hj[m > 0][bit])
        r_exp.append(new[m > 0][bit] - i)
    shares = [(o, new[np.searchsorted(hj, o)]) for o in ids]
    return (np.concatenate(r_job), np.concatenate(r_exp)), shares


def new_job(parts: int) -> tuple[int, list[int]]:
    """A new job's credit 1 divided among `parts` packages, as `split`
    divides it, in closed form (the server does this once per job, where
    `split`'s array work would cost more than the job's routing):
    (each package's exponent, the exponents the server keeps)."""
    if parts == 0:
        return 0, [0]                                # nothing sent: all of it kept
    b = parts.bit_length()
    rem = (1 << b) - parts
    return b, [b - i for i in range(b) if rem >> i & 1]


class Account:
    """The credit returned for one job: numerator / 2**exp, exactly."""
    __slots__ = ("num", "exp")

    def __init__(self):
        self.num, self.exp = 0, 0

    def add(self, exps) -> None:
        top = max(self.exp, *exps)
        num = self.num << (top - self.exp)
        for e in exps:
            num += 1 << (top - e)
        self.num, self.exp = num, top
        while self.exp and not self.num & 1:        # keep the integers small
            self.num >>= 1
            self.exp -= 1

    @property
    def complete(self) -> bool:
        return self.num >= 1 << self.exp

    @property
    def over(self) -> bool:
        """More than the whole returned: a duplicated message (a bug)."""
        return self.num > 1 << self.exp


def by_job(job: np.ndarray, exp: np.ndarray) -> dict[int, list[int]]:
    """Returned terms grouped by job id."""
    out: dict[int, list[int]] = {}
    for j, e in zip(np.asarray(job).tolist(), np.asarray(exp).tolist()):
        out.setdefault(j, []).append(e)
    return out
