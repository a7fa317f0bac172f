"""Exactly-once, checked from outside the server (services/ledger.py, issue
15): the server's ledger names the eye iterations and photon jobs it
applied; re-tracing exactly those in one process, by one tracer state
serving every chunk (no server, transport or accounting), must give the
server's totals (deposits, their flux, N and tau
summed over the pixels, N_e, hit points).

The negative controls are faulty transports: one that sends the deposits
of a results message twice, one that delivers a whole message twice, and
one that drops the deposits of one. Each must fail the
check, naming what differs. The fault tests with real processes
(test_faults.py, test_netns_faults.py) run the same check."""
from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from services import ledger
from services.inproc import InProcessCluster
from services.wire import Message
from tests.helpers.chunks import MemoryChunks, root_box, uniform_tree
from tests.helpers.cluster import caustic_scene, settings

PHOTONS = 120_000


def _render(chunks=(1, 1, 1), tracers=2, photons=PHOTONS, kill_at=None, **kw):
    """(the chunks rendered, the cluster), after a render to `photons`."""
    scene = caustic_scene()
    provider = MemoryChunks(scene, uniform_tree(root_box(scene), chunks))
    # Small batches: several statistics updates, applied in the ledger's order.
    c = InProcessCluster(provider, dataclasses.replace(settings(), photon_batch=40_000), tracers=tracers, **kw)
    try:
        if kill_at is not None:
            c.render(photons=kill_at)
            c.kill("t0")
        c.run(photons=photons)
    finally:
        c.close()
    return provider, c


def _results_with_deposits(sender, dest, msg):
    return msg.type == "results" and msg.deposits is not None and len(msg.deposits) > 0


@pytest.mark.parametrize("chunks", [(1, 1, 1), (2, 2, 1)], ids=["c=1", "c=4"])
def test_a_render_agrees_with_its_ledger_retraced(chunks):
    provider, c = _render(chunks)
    records = c.statistics.ledger.records
    end = records[-1]["totals"]
    assert end["photons_emitted"] >= PHOTONS and end["deposits"] > 0
    assert sum(r["kind"] == "photons" for r in records) >= 2     # several batches, in order
    assert ledger.check(provider, records) == []


def test_a_killed_tracer_leaves_the_ledger_exact():
    provider, c = _render(tracers=3, kill_at=40_000, tracer_timeout_s=2.0)
    assert c.server.counters["tracers_evicted"] == 1 and c.server.counters["jobs_discarded"] > 0
    assert ledger.check(provider, c.statistics.ledger.records) == []


def test_a_tracer_lost_while_draining_leaves_the_drain_to_finish():
    """Evicted after the last job was emitted: its jobs are re-emitted and
    sent during the drain (they once held it until its timeout)."""
    scene = caustic_scene()
    provider = MemoryChunks(scene, uniform_tree(root_box(scene), (1, 1, 1)))
    c = InProcessCluster(provider, dataclasses.replace(settings(), photon_batch=40_000), tracers=3,
                         tracer_timeout_s=2.0)
    try:
        c.render(photons=PHOTONS)
        c.server.stop_emitting()
        c.kill("t1")
        c.drain()
    finally:
        c.close()
    k = c.server.counters
    assert k["tracers_evicted"] == 1 and k["jobs_discarded"] > 0
    assert k["photons_emitted"] - k["photons_discarded"] == k["photons_completed"] == k["photons_committed"]
    assert ledger.check(provider, c.statistics.ledger.records) == []


class _Once:
    """A faulty transport: `fault(msg)` on the first results message that
    carries deposits (after `skip` of them), the rest delivered as sent."""

    def __init__(self, fault, skip=3):
        self.fault, self.skip, self.done = fault, skip, False

    def __call__(self, sender, dest, msg):
        if self.done or not _results_with_deposits(sender, dest, msg):
            return [msg]
        if self.skip:
            self.skip -= 1
            return [msg]
        self.done = True
        return self.fault(msg)


def _with_deposits(msg: Message, deposits) -> Message:
    return Message(msg.type, dict(msg.fields, deposits=deposits))


@pytest.mark.parametrize("fault, what", [
    (lambda msg: [_with_deposits(msg, type(msg.deposits).concat([msg.deposits, msg.deposits]))],
     "the deposits of one results message sent twice"),
    (lambda msg: [_with_deposits(msg, msg.deposits.take(np.zeros(0, np.int64)))],
     "the deposits of one results message dropped"),
    # The copy finds its jobs complete (the first returned all their
    # credit): its deposits are dropped as late, which the check flags.
    (lambda msg: [msg, msg], "a results message delivered twice"),
], ids=["duplicated", "dropped", "delivered twice"])
def test_a_faulty_transport_fails_the_ledger_check(fault, what):
    tamper = _Once(fault)
    provider, c = _render(tamper=tamper)
    assert tamper.done, f"the control never fired: {what}"
    problems = ledger.check(provider, c.statistics.ledger.records)
    assert any(p.startswith(("deposits:", "deposits_late:")) for p in problems), (what, problems)


def test_the_ledger_file_round_trips(tmp_path):
    provider, c = _render(photons=40_000)
    path = tmp_path / "render.ledger"
    book = ledger.Ledger(c.settings, (64, 64), str(path))
    for rec in c.statistics.ledger.records[1:]:
        book._write(rec)
    records = ledger.read(str(path))
    assert [r["kind"] for r in records] == [r["kind"] for r in c.statistics.ledger.records]
    assert ledger.check(provider, records) == []


def test_a_file_that_is_no_ledger_is_refused_in_one_line(tmp_path):
    bad = tmp_path / "x.ledger"
    bad.write_bytes(b"\x93not msgpack at all")
    with pytest.raises(ledger.LedgerError, match="x.ledger: not a ledger"):
        ledger.read(str(bad))
