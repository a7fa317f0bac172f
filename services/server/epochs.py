"""The server's side of the gather at the tracers (issue 32 step 3; the
derivation is in docs/how-it-works.md, "The gather at the tracers").

Photon job ids are cut into epochs of `jobs_per_epoch` ids. Tracers keep
the deposits of each epoch (services/tracer/epochs.py); the server keeps
here, per epoch, the photon jobs made in it and which are complete. An
epoch is due once no job of it can still be made or run (the ids past it
are in use, or emission stopped, and none of its jobs is in flight), and
every epoch before it is applied or discarded: eqs. 1-5 need a batch
gathered at the radii it is applied to, so epochs are applied one at a
time, in order. Its gather is then asked of every live tracer, in the
rounds of `wire.GATHER_PHASES`, and once all have answered the last
round its summed sums are one statistics update.

Exactly-once by construction: an epoch is applied whole or not at all.
A tracer lost while epochs are unapplied may have held deposits of any of
them, so all of them are discarded (`discard_unapplied`) and their jobs
made again under new ids, past every discarded epoch.

Pure: no sockets, no statistics; `ServerState` drives it.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

# HIT_POINT_BYTES: one hit point on the wire, once (76 B with its frame, in
# scenes with an anisotropic material; 56 without, the bound counts those).
from dosppm_core.chunks.pacing import DEPOSIT_BYTES, HIT_POINT_BYTES
from dosppm_core.sppm.statistics import add_rows
from dosppm_core.trace import NO_CULL

# What an epoch brings into the server, at most, per photon (issue 32's
# target), with every hit point reached: each tracer's sums and the light
# of its eye iterations (a round an epoch, `hit_point_stride`), and the
# one set of hit points the epoch is gathered at.
BYTES_PER_PHOTON = 8.0
# Epochs photon jobs may be made in, from the next one to apply, at least:
# the one being gathered and two filling behind it keep the tracers busy
# while a gather's rounds travel, and bound what they hold to about three
# epochs' deposits however slowly the gathers go (a saturated link, a slow
# tracer). Merged gathers widen it (`Epochs.window`).
OPEN_EPOCHS = 3
# Epochs one gather may merge, by default (`--batch-growth`): the
# statistics batch grows to this many epochs while the tracers finish
# epochs faster than the server's rounds gather them.
MOST_MERGED = 8
DENSE_SUMS_BYTES = 32            # M and Phi (f64) of one hit point, from one tracer
LIGHT_BYTES = 16                 # a pixel's light in a round, from one tracer (pixel i32, rgb f32)


def jobs_per_epoch(photon_batch: int, photons_per_job: int, tracers: int, pixels: int) -> int:
    """About `photon_batch` photons an epoch (server batching, §4.3), grown
    until what it brings into the server over `pixels` pixels (a hit point
    each, at most), from `tracers` tracers, is at most BYTES_PER_PHOTON a
    photon. Every tracer's answer costs the same, so this grows with the
    cluster: a reduction among the tracers would not."""
    per_pixel = tracers * (DENSE_SUMS_BYTES + LIGHT_BYTES) + HIT_POINT_BYTES
    photons = max(int(photon_batch), int(np.ceil(pixels * per_pixel / BYTES_PER_PHOTON)))
    return max(1, -(-photons // max(1, int(photons_per_job))))


@dataclass
class Epoch:
    index: int                      # its first epoch; a merged gather's runs to `last`
    made: int = 0                   # photon jobs made in it, not yet complete or dropped
    jobs: dict = field(default_factory=dict)   # complete: id -> (rng key, paths, cull box)
    phase: str | None = None        # the round asked, None before the first
    asked_s: float | None = None    # when that round was asked
    waiting: set = field(default_factory=set)  # tracers whose answer to it is not in
    sums: dict = field(default_factory=dict)   # the round's answers, by tracer (`total`)
    fit: tuple | None = None        # radii fitted by its pilot, stored when it is applied
    rows: int = 0                   # the rows the round asked sums for (each answer's M and Phi)
    last: int = -1                  # the last epoch merged into it (`Epochs.due`); -1: itself
    first_asked_s: float | None = None     # when its first round was asked

    def __post_init__(self):
        if self.last < self.index:
            self.last = self.index

    @property
    def count(self) -> int:
        """Epochs it gathers: 1, or more once merged."""
        return self.last - self.index + 1

    @property
    def indices(self) -> range:
        """The epochs it gathers."""
        return range(self.index, self.last + 1)

    def merge(self, later: "Epoch") -> None:
        """The next epoch's jobs, gathered and applied with these as one batch."""
        assert later.index == self.last + 1 and later.made == 0 and self.phase is None
        self.jobs.update(later.jobs)
        self.last = later.index

    def columns(self) -> tuple:
        """(ids, rng keys, paths, cull boxes (n, 2, 3)) of its complete jobs, by id."""
        ids = sorted(self.jobs)
        keys = np.array([self.jobs[j][0] for j in ids], np.int64)
        paths = np.array([self.jobs[j][1] for j in ids], np.int64)
        boxes = np.array([NO_CULL if self.jobs[j][2] is None else self.jobs[j][2] for j in ids],
                         np.float64).reshape(-1, 2, 3)
        return np.array(ids, np.int64), keys, paths, boxes


class Epochs:
    """`most_merged`: epochs one gather may merge (1: every epoch its own
    batch). `held_bytes`: what the tracers' held deposits may take, all
    together, which bounds the window merged gathers widen (None: no bound)."""

    def __init__(self, jobs_per_epoch: int, first_job: int = 0, most_merged: int = 1,
                 held_bytes: float | None = None):
        if most_merged < 1:
            raise ValueError(f"most_merged (--batch-growth) must be >= 1, got {most_merged}")
        self.jobs_per_epoch = int(jobs_per_epoch)
        self.most_merged, self.held_bytes = int(most_merged), held_bytes
        self.open: dict[int, Epoch] = {}
        self.next = self.of(first_job)         # the next epoch to apply
        self.discarded: set[int] = set()
        self.asking = False                    # an epoch's gather is under way
        self.merged = 1                        # epochs the last gather merged
        self.deposit_bytes = 0.0               # held per epoch, as the last gather counted
        self.gather_s = 0.0                    # the last gather, from its first round asked to applied
        self.counters = {"epochs_applied": 0, "epochs_discarded": 0, "epoch_rounds": 0, "epoch_gathers": 0,
                         "epochs_merged_most": 1}

    def of(self, job: int) -> int:
        return int(job) // self.jobs_per_epoch

    def first_id_after(self, epoch: int) -> int:
        return (int(epoch) + 1) * self.jobs_per_epoch

    def room_for(self, j: int) -> bool:
        """Whether photon job id `j` may be made now (`window`)."""
        return self.of(j) < self.next + self.window()

    def window(self) -> int:
        """Epochs photon jobs may be made in, from the next to apply: room
        for the gather under way and twice as many behind it, so a gather
        that merged g epochs is followed by one of up to 2g while the
        tracers outpace the rounds (the batch doubles, 1, 2, 4, 8: one
        more epoch a gather took seven gathers to reach 8, most of a
        30 s render); never more than the tracers may hold."""
        w = max(OPEN_EPOCHS, 3 * self.merged)
        if self.held_bytes and self.deposit_bytes > 0:
            w = min(w, max(OPEN_EPOCHS, int(self.held_bytes // self.deposit_bytes)))
        return w

    def made(self, j: int) -> None:
        self._epoch(self.of(j)).made += 1

    def dropped(self, j: int) -> None:
        """A photon job that will never complete (never sent, or abandoned)."""
        e = self.open.get(self.of(j))
        if e is not None:
            e.made -= 1

    def complete(self, j: int, rng_key: int, paths: int, cull_box) -> None:
        e = self._epoch(self.of(j))
        e.made -= 1
        e.jobs[int(j)] = (int(rng_key), int(paths), cull_box)

    def _epoch(self, index: int) -> Epoch:
        if index not in self.open:
            self.open[index] = Epoch(index)
        return self.open[index]

    def due(self, next_job: int, emitting: bool) -> Epoch | None:
        """The next epoch to gather, if it is due and none is being gathered."""
        if self.asking:
            return None
        while self.next in self.discarded or (self.next not in self.open and self.next < self.of(next_job)):
            if self.next in self.discarded:
                self.next += 1
                continue
            # No photon job was ever made in it (eye jobs' ids, or the ids a
            # resumed server skipped: 2^40 of them, so jump, never step).
            later = [e for e in self.open if e > self.next]
            self.next = min(later) if later else self.of(next_job)
        e = self.open.get(self.next)
        if e is None or e.made > 0:
            return None
        if emitting and next_job < self.first_id_after(e.index):
            return None             # more of its jobs may still be made
        if not e.jobs:              # every job of it dropped: nothing to gather
            del self.open[e.index]
            self.next += 1
            return self.due(next_job, emitting)
        self._merge_complete(e, next_job, emitting)
        self.asking = True
        return e

    def _merge_complete(self, e: Epoch, next_job: int, emitting: bool) -> None:
        """Merge into `e` the epochs after it that are complete too, up to
        `most_merged`: the tracers finished them while the last gather's
        rounds travelled, so the round trips, not the tracers, hold the
        render, and one gather of them all costs the round trips of one.
        While the tracers are what holds it, the next epoch is not complete
        when its turn comes, and each epoch is its own batch, the paper's."""
        while e.count < self.most_merged:
            later = self.open.get(e.last + 1)
            if later is None or later.made > 0 or (emitting and next_job < self.first_id_after(later.index)):
                break
            e.merge(later)
            del self.open[later.index]
        self.merged = e.count
        self.counters["epochs_merged_most"] = max(self.counters["epochs_merged_most"], e.count)

    def ask(self, e: Epoch, phase: str, tracers, now: float, rows: int = 0) -> None:
        """Round `phase` of epoch `e`, sums at `rows` rows, goes to `tracers`;
        answers are added up."""
        e.phase, e.waiting, e.sums, e.asked_s, e.rows = phase, set(tracers), {}, now, int(rows)
        if e.first_asked_s is None:
            e.first_asked_s = now
        self.counters["epoch_rounds"] += 1

    def round_waiting_since(self, now: float) -> float:
        """Seconds the round under way has waited for answers (0: none waits)."""
        waiting = [now - e.asked_s for e in self.open.values() if e.waiting and e.asked_s is not None]
        return max(waiting, default=0.0)

    def answer(self, tid: str, msg) -> Epoch | None:
        """A tracer's `epoch_sums`; the epoch once every answer to its round
        is in (None while some are missing, or for a stale answer)."""
        e = self.open.get(msg.epoch)
        if e is None or msg.phase != e.phase or tid not in e.waiting:
            return None              # a discarded epoch's, or an earlier round's
        problem = _rows_problem(msg, e.rows)
        if problem:                  # not taken: the watchdog discards the round unanswered
            raise ValueError(f"epoch_sums: epoch {e.index}: {problem}")
        e.waiting.discard(tid)
        e.sums[tid] = msg
        return e if not e.waiting else None

    def applied(self, e: Epoch, deposits: int = 0, now: float | None = None) -> None:
        """Epoch `e` (and those merged into it) applied at `now`, `deposits` held for them."""
        del self.open[e.index]
        self.next, self.asking = e.last + 1, False
        self.deposit_bytes = DEPOSIT_BYTES * deposits / e.count
        if now is not None and e.first_asked_s is not None:
            self.gather_s = max(0.0, now - e.first_asked_s)
        self.counters["epochs_applied"] += e.count
        self.counters["epoch_gathers"] += 1

    def drain_s(self) -> float:
        """Seconds the epochs not yet applied take once emission stops: the
        gather under way, then the rest, merged `most_merged` at a time,
        each as long as the last gather took. A time limit counts it:
        photons of an epoch unapplied at the deadline are lost work."""
        n = len(self.open)
        return self.gather_s * (1 + -(-(n - 1) // self.most_merged)) if n else 0.0

    def discard_unapplied(self) -> list[Epoch]:
        """Every epoch not yet handed to the statistics: (their jobs to make
        again). The round under way, if any, is forgotten with it."""
        lost = [e for e in self.open.values() if e.phase != "applying"]
        for e in lost:
            del self.open[e.index]
            self.discarded.update(e.indices)
        self.asking = any(e.phase == "applying" for e in self.open.values())
        self.counters["epochs_discarded"] += sum(e.count for e in lost)
        return lost

    @property
    def unapplied(self) -> int:
        return len(self.open)


def _rows_problem(msg, n: int) -> str | None:
    """Why an answer's sums do not fit the `n` rows its round asked for
    (the sums are added into arrays of `n` rows without a bounds check)."""
    if msg.phase == "count":
        return None
    rows = msg.fields.get("rows")
    if rows is None and len(msg.m) != n:
        return f"field 'm' has {len(msg.m)} rows, the round asked for {n}"
    if rows is not None and len(rows) and rows[-1] >= n:
        return f"field 'rows' reaches row {int(rows[-1])}, the round asked for {n}"
    return None


def total(answers: dict, n: int) -> dict:
    """A round's answers added up, in tracer id order (so a render's sums do
    not depend on which answer came first): deposits, chosen, flux, and M
    and Phi over `n` rows (sparse answers spread to every row)."""
    out = {"deposits": 0, "chosen": 0, "flux": np.zeros(3), "m": np.zeros(n), "phi": np.zeros((n, 3))}
    for tid in sorted(answers):
        msg = answers[tid]
        out["deposits"] += int(msg.deposits)
        out["chosen"] += int(msg.chosen)
        out["flux"] = out["flux"] + np.asarray(msg.flux, np.float64)
        if msg.phase == "count":
            continue
        rows = msg.fields.get("rows")
        if rows is None:
            out["m"] += msg.m
            out["phi"] += msg.phi
        else:                             # rows are distinct (the wire checks they increase)
            add_rows(out["m"], rows, msg.m)
            add_rows(out["phi"], rows, msg.phi)
    return out
