"""Chunks re-assigned by measured work (services/server/balance.py): the
table it picks, when it leaves the table alone, the server sending it,
and exactly-once across chunks moving mid-render."""
from __future__ import annotations

import dataclasses

import pytest

from services import ledger
from services.inproc import InProcessCluster
from services.server import balance, membership, state as server_state
from services.server.balance import assign_chunks, busiest_share, by_work, rebalanced
from tests.helpers.chunks import MemoryChunks, root_box, uniform_tree
from tests.helpers.cluster import caustic_scene, settings
from tests.test_scheduler import _msg, _register, new_state

TWO = {"a": 1, "b": 1}


def _statuses(owners, work):
    """Each tracer's report: the rays (millions of `work`) of its chunks."""
    return {t: {"rays_by_chunk": [[k, int(work[k] * 1e6)] for k, o in enumerate(owners) if o == [t]],
                "holds_every_chunk": True} for t in TWO}


def _flat(owners):
    return [o[0] for o in owners]


def test_the_balance_longest_first_misses_is_found():
    # Longest first: a gets 3 + 2 + 2 = 7, b 3 + 2 = 5; a swap evens it.
    work = [3.0, 3.0, 2.0, 2.0, 2.0]
    owners = by_work(work, TWO)
    assert busiest_share(owners, work, TWO) == pytest.approx(1.0)
    assert by_work(work, TWO) == owners                          # the same work, the same table
    # From a table, few moves: round robin (a: 3, 2, 2; b: 3, 2) needs one swap.
    start = _flat(assign_chunks(5, ["a", "b"]))
    moved = by_work(work, TWO, start=start)
    assert busiest_share(moved, work, TWO) == pytest.approx(1.0)
    assert sum(x != y for x, y in zip(moved, start)) == 2


def test_a_tracer_with_twice_the_cores_gets_twice_the_work():
    work = [1.0] * 6
    owners = by_work(work, {"a": 2, "b": 1})
    assert owners.count("a") == 4 and owners.count("b") == 2


def test_an_uneven_round_robin_is_replaced():
    owners = assign_chunks(4, ["a", "b"])                     # a: 0, 2; b: 1, 3
    work = [4.0, 1.0, 3.0, 1.0]
    new = rebalanced(owners, _statuses(owners, work), TWO)
    assert new is not None and busiest_share(_flat(new), work, TWO) < busiest_share(_flat(owners), work, TWO)
    assert sorted(sum(work[k] for k, o in enumerate(new) if o == [t]) for t in TWO) == [4.0, 5.0]


@pytest.mark.parametrize("case", ["balanced", "unmeasured", "no report", "out of core", "shared chunks"])
def test_a_table_is_left_alone_when_moving_cannot_pay(case):
    owners = assign_chunks(4, ["a", "b"])
    work = [1.0, 1.0, 1.0, 1.0] if case == "balanced" else [4.0, 1.0, 3.0, 1.0]
    if case == "unmeasured":
        work = [w * balance.MIN_MEASURED_RAYS / 20e6 for w in work]
    statuses = _statuses(owners, work)
    if case == "no report":
        statuses["b"] = {}
    if case == "out of core":
        statuses["b"]["holds_every_chunk"] = False
    if case == "shared chunks":
        owners = assign_chunks(1, ["a", "b"])
        statuses = {t: {"rays_by_chunk": [[0, 5_000_000]], "holds_every_chunk": True} for t in TWO}
    assert rebalanced(owners, statuses, TWO) is None


def _heartbeat(state, tid, rays_by_chunk, now):
    status = {"rays_by_chunk": rays_by_chunk, "holds_every_chunk": True}
    state.on_message(tid, _msg("heartbeat", status=status), now)


def test_the_server_sends_every_tracer_the_rebalanced_table():
    state = new_state()                  # 4 chunks
    _register(state, "a")
    _register(state, "b")
    state.tick(0.0)
    state.tick(1.0)                      # the first heartbeat round of the render: the clock starts
    assert state.started and state.owners == [["a"], ["b"], ["a"], ["b"]]
    work = [4e6, 1e6, 3e6, 1e6]
    _heartbeat(state, "a", [[0, work[0]], [2, work[2]]], 1.5)
    _heartbeat(state, "b", [[1, work[1]], [3, work[3]]], 1.5)
    out = state.tick(1.0 + balance.FIRST_REBALANCE_S / 2)
    assert not [o for o in out if o.type == "peers"]          # not yet: too soon after the start
    version = state.table_version
    out = state.tick(1.5 + balance.FIRST_REBALANCE_S)
    peers = [o for o in out if o.type == "peers"]
    assert {o.dest for o in peers} == {"a", "b"} and state.counters["rebalanced"] == 1
    assert all(o.fields["table_version"] == version + 1 for o in peers)
    assert sorted(sum(work[k] for k, o in enumerate(state.owners) if o == [t]) for t in TWO) == [4e6, 5e6]
    _heartbeat(state, "a", [[0, work[0]], [2, work[2]]], 3.0 + balance.REBALANCE_INTERVAL_S)
    _heartbeat(state, "b", [[1, work[1]], [3, work[3]]], 3.0 + balance.REBALANCE_INTERVAL_S)
    out = state.tick(3.0 + balance.REBALANCE_INTERVAL_S)      # balanced now: left alone
    assert not [o for o in out if o.type == "peers"] and state.counters["rebalanced"] == 1


def test_chunks_moved_mid_render_leave_every_photon_applied_once(monkeypatch):
    """Every 0.05 s of cluster time each chunk moves to the other tracer:
    packages queued for it are handed over, packages on their way are
    forwarded, and the ledger re-traced in one process still agrees."""
    moves = []

    def swap(owners, statuses, cores):
        moves.append(len(moves))
        ids = list(cores)
        return [[ids[(ids.index(o[0]) + 1) % len(ids)]] for o in owners]
    monkeypatch.setattr(membership, "rebalanced", swap)
    for module in (server_state, membership):       # cluster time runs 10 ms a round
        monkeypatch.setattr(module, "HEARTBEAT_INTERVAL_S", 0.02)
    monkeypatch.setattr(membership, "REBALANCE_INTERVAL_S", 0.05)
    monkeypatch.setattr(membership, "FIRST_REBALANCE_S", 0.05)
    scene = caustic_scene()
    provider = MemoryChunks(scene, uniform_tree(root_box(scene), (2, 2, 1)))
    c = InProcessCluster(provider, dataclasses.replace(settings(), photon_batch=40_000), tracers=2)
    try:
        c.run(photons=120_000)
    finally:
        c.close()
    assert len(moves) >= 3 and c.server.counters["rebalanced"] == len(moves)
    assert sum(t.counters["forwarded_rays"] for t in c.tracers.values()) > 0
    assert ledger.check(provider, c.statistics.ledger.records) == []
