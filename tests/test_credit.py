"""Credit (services/credit.py): a job is complete when the credit its
packages carried has all come back, so no results message with its
deposits can still be on its way. The race that counting ended paths lost
(issue 15): a step whose paths all leave its chunk ends none, and the
downstream tracer's report can reach the server before its message."""
from __future__ import annotations

import dataclasses
from fractions import Fraction

import numpy as np
import pytest

from services import credit, ledger, wire
from services.inproc import InProcessCluster
from tests.helpers.chunks import MemoryChunks, root_box, uniform_tree
from tests.helpers.cluster import caustic_scene, settings
from tests.helpers.credit import credit_sum


def _value(job, exp) -> dict[int, Fraction]:
    return credit_sum([(job, exp)])


@pytest.mark.parametrize("seed", range(20))
def test_a_split_conserves_credit_exactly_and_returns_some_of_every_job(seed):
    rng = np.random.default_rng(seed)
    jobs = rng.choice(50, int(rng.integers(1, 8)), replace=False)
    job = np.repeat(jobs, rng.integers(1, 4, len(jobs)))          # coalesced packages: several terms
    exp = rng.integers(0, 40, len(job))
    outgoing = [rng.choice(jobs, int(rng.integers(1, 30))) for _ in range(int(rng.integers(0, 9)))]
    (r_job, r_exp), shares = credit.split(job, exp, outgoing)
    before, returned = _value(job, exp), _value(r_job, r_exp)
    after = dict(returned)
    for (s_job, s_exp), o in zip(shares, outgoing):
        assert sorted(s_job.tolist()) == sorted(set(o.tolist()))   # one term per job carried
        for j, v in _value(s_job, s_exp).items():
            after[j] = after.get(j, Fraction(0)) + v
    assert after == before
    assert set(returned) == set(before) and all(v > 0 for v in returned.values())


@pytest.mark.parametrize("parts", range(0, 13))
def test_a_new_jobs_closed_form_division_is_splits(parts):
    exp, kept = credit.new_job(parts)
    (r_job, r_exp), shares = credit.split([5], [0], [np.full(3, 5)] * parts)
    assert sorted(kept) == sorted(r_exp.tolist())
    assert all(s_exp.tolist() == [exp] for _, s_exp in shares)


def test_rays_leaving_for_a_job_without_credit_are_refused():
    with pytest.raises(ValueError, match="no credit"):
        credit.split(np.array([1]), np.array([0]), [np.array([1, 2])])


def test_an_account_is_complete_exactly_at_one():
    a = credit.Account()
    a.add([1, 2])
    assert not a.complete
    a.add([3, 3])
    assert a.complete and not a.over
    a.add([60])
    assert a.over


def test_the_wire_refuses_exponents_past_the_cap():
    one = np.array([3], np.int64)
    fields = dict(job_ids=one, rng_keys=one, counts=one, cull_box=np.zeros((2, 3)),
                  credit_job=one, credit_exp=np.array([credit.MAX_EXP + 1], np.int64))
    with pytest.raises(wire.WireError, match="photon_job: field 'credit_exp'"):
        wire.decode([bytes(f) for f in wire.encode("photon_job", **fields)])


class _Reorder:
    """A transport that holds back, for a few messages, every results
    message with deposits of a job whose step ended none of its paths (all
    went on through portals), so the downstream tracer's report of those
    paths may reach the server first. It keeps the
    old count of open path segments per photon job (paths sent, plus paths
    left, minus paths fed, in the order the server gets them; an emission
    feeds them all and passes on those that start in the scene) to count the
    deposits that counting would have dropped as late."""

    def __init__(self, delay=20):
        self.delay, self.held, self.open, self.would_be_late = delay, [], {}, 0

    def __call__(self, sender, dest, msg):
        """The messages to deliver from `sender` to `dest` now (the cluster
        delivers what this returns on that route: held ones are released
        only with a later message of their own tracer to the server)."""
        if msg.type == "photon_job":
            for j, n in zip(msg.job_ids.tolist(), msg.counts.tolist()):
                self.open[j] = self.open.get(j, 0) + n
        if dest != "server":
            return [msg]
        for entry in self.held:
            entry[0] -= 1
        due = [e for e in self.held if e[1] == sender and (e[0] <= 0 or msg.type == "heartbeat")]
        self.held = [e for e in self.held if not any(e is d for d in due)]
        out = [self._arrives(e[2]) for e in due]
        if msg.type == "results" and _ends_none_of_a_depositing_job(msg):
            self.held.append([self.delay, sender, msg])
        else:
            out.append(self._arrives(msg) if msg.type == "results" else msg)
        return out

    def _arrives(self, msg):
        if msg.deposits is not None:
            done = [j for j in np.unique(msg.deposits.job).tolist() if self.open.get(j, 1) == 0]
            self.would_be_late += int(np.isin(msg.deposits.job, done).sum())
        for j, fed, left in zip(msg.job_ids.tolist(), msg.job_fed.tolist(), msg.job_left.tolist()):
            if j in self.open:
                self.open[j] += left - fed
        return msg


def _ends_none_of_a_depositing_job(msg) -> bool:
    if msg.deposits is None:
        return False
    passed_on = msg.job_ids[msg.job_fed == msg.job_left]
    return bool(np.isin(passed_on, msg.deposits.job).any())


def test_a_downstream_report_that_overtakes_its_upstream_one_loses_nothing():
    scene = caustic_scene()
    provider = MemoryChunks(scene, uniform_tree(root_box(scene), (2, 2, 1)))
    reorder = _Reorder()
    # Jobs of 8 photons: a step often takes all of a job's paths in its
    # chunk and ends none of them, the condition of the race.
    c = InProcessCluster(provider, dataclasses.replace(settings(), photon_batch=20_000, photons_per_job=8),
                         tracers=2, tamper=reorder)
    try:
        c.run(photons=60_000)
    finally:
        c.close()
    assert reorder.would_be_late > 1000, "the race never happened: the test proves nothing"
    k = c.server.counters
    assert k["deposits_late"] == 0 and k["over_credited_jobs"] == 0
    assert k["photons_emitted"] == k["photons_completed"] == k["photons_committed"]
    assert ledger.check(provider, c.statistics.ledger.records) == []
