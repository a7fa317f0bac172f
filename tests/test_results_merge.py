"""Accounting-only results merged at the tracer (services/tracer/merge.py,
issue 32): one message that the wire accepts and that gives the server's
exact accounting the same paths ended, ends and credit per job as the
messages it replaces."""
from __future__ import annotations

import numpy as np

from dosppm_core.jobs import END_NAMES, HitPoints
from services import wire
from services.credit import Account, by_job, split
from services.tracer.merge import MergedResults, mergeable, merged


def _results(rng, job, exp, chunk):
    """A step's results for paths of `job` (one credit term 2**-exp per
    job, by id): some paths leave in a package, the rest end; its credit
    split as a tracer splits it."""
    leaving = job[rng.random(len(job)) < 0.3]
    (cj, ce), shares = split(np.unique(job), exp, [leaving] if len(leaving) else [])
    ids, fed = np.unique(job, return_counts=True)
    left = np.array([np.sum(leaving == j) for j in ids], np.int64)
    ends = np.zeros(len(END_NAMES), np.int64)
    ends[1:] = np.bincount(rng.integers(0, len(END_NAMES) - 1, int((fed - left).sum())),
                           minlength=len(END_NAMES) - 1)
    fields = dict(chunk=chunk, ends=ends, culled=int(rng.integers(0, 9)), job_ids=ids, job_fed=fed,
                  job_left=left, credit_job=cj, credit_exp=ce, queued=int(rng.integers(0, 1000)),
                  queue_target=0)
    return fields, shares


def _credit(parts):
    acc = {}
    for p in parts:
        for j, e in by_job(p["credit_job"], p["credit_exp"]).items():
            acc.setdefault(j, Account()).add(e)
    return {j: (a.num, a.exp) for j, a in acc.items()}


def _ended(parts):
    out = {}
    for p in parts:
        for j, f, l in zip(p["job_ids"].tolist(), p["job_fed"].tolist(), p["job_left"].tolist()):
            out[j] = out.get(j, 0) + f - l
    return out


def test_merged_results_account_for_exactly_what_the_parts_did():
    rng = np.random.default_rng(4)
    parts = []
    for step in range(6):
        job = np.repeat(np.sort(rng.choice(np.arange(100, 110), 3, replace=False)).astype(np.int64), 500)
        fields, _ = _results(rng, job, np.full(3, 2, np.int64), chunk=step % 2)
        parts.append(fields)
    assert all(mergeable(p) for p in parts)
    m = merged(parts)
    msg = wire.decode(wire.encode("results", **m))        # the wire takes it whole
    assert _credit([m]) == _credit(parts)
    assert _ended([m]) == _ended(parts)
    assert msg.ends.tolist() == np.sum([p["ends"] for p in parts], axis=0).tolist()
    assert msg.culled == sum(p["culled"] for p in parts) and msg.queued == parts[-1]["queued"]
    assert msg.chunk is None                                 # steps in two chunks
    # Fewer terms than the parts carried: the server adds fewer.
    assert len(m["credit_job"]) < sum(len(p["credit_job"]) for p in parts)


def test_a_whole_job_returned_in_pieces_merges_to_one_term():
    job = np.repeat(np.array([7], np.int64), 1000)
    (cj, ce), shares = split(np.array([7], np.int64), np.zeros(1, np.int64), [job[:400], job[400:700]])
    pieces = [dict(chunk=None, ends=np.zeros(len(END_NAMES), np.int64), culled=0,
                   job_ids=np.array([7], np.int64), job_fed=np.array([1000], np.int64),
                   job_left=np.array([700], np.int64), credit_job=cj, credit_exp=ce, queued=0,
                   queue_target=0)]
    pieces[0]["ends"][1] = 300
    for (sj, se), n in zip(shares, (400, 300)):
        ends = np.zeros(len(END_NAMES), np.int64)
        ends[2] = n
        pieces.append(dict(chunk=1, ends=ends, culled=0, job_ids=np.array([7], np.int64),
                           job_fed=np.array([n], np.int64), job_left=np.array([0], np.int64),
                           credit_job=sj, credit_exp=se, queued=0, queue_target=0))
    m = merged(pieces)
    assert m["credit_job"].tolist() == [7] and m["credit_exp"].tolist() == [0]   # credit 1: complete
    assert _ended([m]) == {7: 1000}


def test_held_results_are_due_after_the_hold_and_only_then():
    rng = np.random.default_rng(2)
    held = MergedResults(hold_s=0.05)
    f, _ = _results(rng, np.repeat(np.array([3], np.int64), 10), np.array([0], np.int64), chunk=0)
    assert not held.due(10.0) and held.take() == []
    held.add(f, 10.0)
    assert not held.due(10.04) and held.due(10.05)
    assert held.take() == [f] and not held.due(11.0)


def test_results_of_eye_iterations_merge_per_iteration_with_the_hit_points_made():
    rng = np.random.default_rng(5)
    held = MergedResults()
    parts = {}
    for n, e in enumerate([None, 4, None, 5, 4, 4]):
        f, _ = _results(rng, np.repeat(np.array([10 + n], np.int64), 50), np.array([0], np.int64), chunk=0)
        if e is not None:
            f.update(eye_iteration=e, hits=HitPoints.empty(), hit_points_made=100 + n)
        held.add(f, 1.0)
        parts.setdefault(e, []).append(f)
    last_queued = f["queued"]
    out = held.take()
    assert [m.get("eye_iteration") for m in out] == [None, 4, 5]       # photons first, then by iteration
    for m in out:
        e = m.get("eye_iteration")
        msg = wire.decode(wire.encode("results", **m))
        assert _credit([m]) == _credit(parts[e]) and _ended([m]) == _ended(parts[e])
        assert msg.hit_points_made == sum(p.get("hit_points_made", 0) for p in parts[e])
        assert msg.queued == last_queued                 # the latest queue in every one


def test_results_with_deposits_hit_points_or_light_are_never_merged():
    base = dict(deposits=None, hits=None, emitted_pixels=None, eye_iteration=None)
    assert mergeable(base) and mergeable(dict(base, hits=HitPoints.empty(), eye_iteration=3))
    for k, v in (("deposits", object()), ("hits", np.zeros(2)), ("emitted_pixels", np.zeros(1))):
        assert not mergeable(dict(base, **{k: v}))
