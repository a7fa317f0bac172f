"""The gather at the tracers, by epochs (issue 32 step 3), in process
(`services.inproc`): the image agrees with the server's own gather and with
single-process SPPM within noise, every photon is applied exactly once
(the ledger re-traces the render), and a tracer lost mid-epoch costs its
open epochs, which are made again under new ids, and nothing else."""
from __future__ import annotations

import dataclasses

import numpy as np

import pytest

from services import ledger
from services.inproc import InProcessCluster
from services.server.epochs import total
from tests.helpers.chunks import MemoryChunks, root_box, uniform_tree
from tests.helpers.cluster import assert_same_within_noise, caustic_reference, caustic_scene, settings

PHOTONS = 240_000
BATCH = 60_000      # several epochs (and server batches) in a render of PHOTONS


def _settings(seed=5):
    return dataclasses.replace(settings(seed), photon_batch=BATCH)


@pytest.fixture(scope="module")
def caustic():
    return caustic_scene(), caustic_reference()


def _render(scene, gather_at, tiles=(2, 1, 1), tracers=2, seed=5):
    provider = MemoryChunks(scene, uniform_tree(root_box(scene), tiles))
    c = InProcessCluster(provider, _settings(seed), tracers=tracers, gather_at=gather_at)
    try:
        c.run(photons=PHOTONS)
    finally:
        c.close()
    return provider, c


def test_the_tracers_gather_gives_the_servers_image_and_counts_each_photon_once(caustic):
    scene, ref = caustic
    _, server = _render(scene, "server")
    provider, tracers = _render(scene, "tracers")
    assert_same_within_noise(tracers.image(), ref[5][0], ref[9][0])
    assert_same_within_noise(tracers.image(), server.image(), ref[9][0])
    k, e = tracers.server.counters, tracers.server.epochs
    assert k["photons_emitted"] == k["photons_completed"] == k["photons_committed"] >= PHOTONS
    assert tracers.statistics.stats.photons_emitted == k["photons_committed"]
    assert e.counters["epochs_applied"] >= 3 and not e.open and not tracers.server.jobs
    assert tracers.statistics.deposits_applied == k["deposits_received"] > 0
    # No deposit went to the server; every tracer's held deposits were gathered or dropped.
    assert all(t.epochs.rows == 0 for t in tracers.tracers.values())
    assert ledger.check(provider, tracers.statistics.ledger.records) == []


def test_a_tracer_killed_mid_epoch_costs_its_epochs_and_no_photon(caustic):
    """c = 4 over three tracers; one stops dead with deposits of open
    epochs in its hold. The gather waits for its answer until it is
    evicted; then every unapplied epoch is discarded and its jobs made
    again past it: nothing is lost, nothing counted twice, the ledger
    re-traces the render and the image agrees with SPPM within noise."""
    scene, ref = caustic
    provider = MemoryChunks(scene, uniform_tree(root_box(scene), (2, 2, 1)))
    c = InProcessCluster(provider, _settings(), tracers=3, tracer_timeout_s=2.0, gather_at="tracers")
    c.render(photons=PHOTONS // 3)
    assert c.tracers["t1"].epochs.rows > 0           # it holds deposits of open epochs
    c.kill("t1")
    c.render(photons=PHOTONS)
    c.drain()
    c.close()
    s, k, e = c.server, c.server.counters, c.server.epochs
    assert k["tracers_evicted"] == 1 and "t1" not in s.tracers
    assert e.counters["epochs_discarded"] >= 1 and e.counters["epochs_applied"] >= 1
    assert k["photons_discarded"] > 0
    # Exactly once: what was emitted and not discarded (in flight, or in a
    # discarded epoch) was applied, once.
    assert k["photons_emitted"] - k["photons_discarded"] == k["photons_completed"] == k["photons_committed"]
    assert c.statistics.stats.photons_emitted == k["photons_committed"]
    assert k["over_credited_jobs"] == 0
    assert all(t.epochs.rows == 0 for tid, t in c.tracers.items() if tid != "t1")
    assert ledger.check(provider, c.statistics.ledger.records) == []
    assert_same_within_noise(c.image(), ref[5][0], ref[9][0])


def test_where_one_epoch_is_one_batch_the_images_are_bit_for_bit_equal(caustic):
    """One tracer, one eye iteration, and a batch (and epoch) larger than
    the render: both gathers apply the same deposits, in the same order, at
    the same hit points and radii, once; the images are equal bit for bit."""
    scene, _ = caustic
    s = dataclasses.replace(settings(), photon_batch=10_000_000, photons_per_iteration=10_000_000)
    images = {}
    for gather_at in ("server", "tracers"):
        c = InProcessCluster(MemoryChunks(scene, uniform_tree(root_box(scene), (1, 1, 1))), s, tracers=1,
                             gather_at=gather_at)
        try:
            c.run(photons=200_000)
        finally:
            c.close()
        assert c.statistics.sppm.updates == 1
        images[gather_at] = c.image()
    assert (images["server"] == images["tracers"]).all()


def test_epochs_go_in_order_and_skip_ids_never_used_at_once():
    """A resumed server's ids start 2^40 on (checkpoint.claim_job_ids):
    the epochs in between, where no photon job was made, are skipped in
    one step; an epoch is due only once no job of it can still be made
    or run, and only after the one before it is applied."""
    from services.server.epochs import Epochs
    e = Epochs(jobs_per_epoch=4)
    first = 1 << 40
    for j in range(first, first + 6):
        e.made(j)
    assert e.due(first + 6, emitting=True) is None       # its jobs are in flight
    for j in range(first, first + 4):
        e.complete(j, rng_key=j, paths=10, cull_box=None)
    due = e.due(first + 6, emitting=True)
    assert due is not None and due.index == first // 4 and sorted(due.jobs) == list(range(first, first + 4))
    assert e.due(first + 6, emitting=True) is None       # one epoch at a time
    e.applied(due)
    for j in (first + 4, first + 5):
        e.complete(j, rng_key=j, paths=10, cull_box=None)
    assert e.due(first + 6, emitting=True) is None       # ids of it may still be made
    assert e.due(first + 6, emitting=False).index == first // 4 + 1


def test_complete_epochs_merge_into_one_gather_within_the_window_and_the_memory():
    """When an epoch's turn comes and the epochs after it are complete too
    (the tracers outpaced the last gather's round trips), one gather takes
    them all, up to `most_merged`; an epoch with a job in flight, or ids
    still to make, ends the run. The window of ids photon jobs may take
    grows with the merge (3g epochs: the next gather may double), within the held-deposit memory;
    a merged gather discarded drops every epoch in it."""
    from services.server.epochs import OPEN_EPOCHS, Epochs

    def complete(e, ids):
        for j in ids:
            e.made(j)
            e.complete(j, rng_key=j, paths=10, cull_box=None)
    e = Epochs(jobs_per_epoch=2, most_merged=3, held_bytes=44 * 1000)
    assert e.window() == OPEN_EPOCHS
    complete(e, range(0, 8))                    # epochs 0 .. 3
    e.made(8)                                   # epoch 4: a job in flight
    g = e.due(9, emitting=True)
    assert (g.index, g.last, g.count, sorted(g.jobs)) == (0, 2, 3, list(range(6)))     # most_merged
    assert set(e.open) == {0, 3, 4} and e.window() == 9
    e.applied(g, deposits=3 * 100)              # 100 deposits (4,400 B) an epoch: 10 fit
    assert e.next == 3 and e.counters["epochs_applied"] == 3 and e.counters["epoch_gathers"] == 1
    assert e.window() == 9 and e.room_for(2 * (3 + 8)) and not e.room_for(2 * (3 + 9))
    e.deposit_bytes = 44 * 250                  # 4 epochs fit in the tracers' memory
    assert e.window() == 4 and e.room_for(2 * (3 + 3)) and not e.room_for(2 * (3 + 4))
    g = e.due(9, emitting=True)                 # epoch 4 is not complete: 3 alone
    assert (g.index, g.count) == (3, 1) and e.merged == 1 and e.window() == OPEN_EPOCHS
    e.applied(g, deposits=100)
    e.complete(8, rng_key=8, paths=10, cull_box=None)
    complete(e, [9, 10])                        # epochs 4 and 5; 5's id 11 not yet made
    assert e.due(11, emitting=True).count == 1  # 5 may still get a job
    assert e.due(11, emitting=True) is None     # one gather at a time
    # A merged gather lost with a tracer: every epoch in it is discarded.
    f = Epochs(jobs_per_epoch=2, most_merged=8)
    complete(f, range(0, 6))
    g = f.due(6, emitting=False)
    assert g.count == 3
    assert f.discard_unapplied() == [g] and f.discarded == {0, 1, 2}
    assert f.counters["epochs_discarded"] == 3


def test_the_epochs_drain_counts_the_gathers_still_to_come():
    """Once emission stops, the unapplied epochs take the gather under way
    and then one per `most_merged` of the rest, each as long as the last
    gather took from its first round to applied; the deadline adds it."""
    from services.server.epochs import Epochs
    e = Epochs(jobs_per_epoch=1, most_merged=4)
    assert e.drain_s() == 0.0
    for j in range(11):
        e.made(j)
        e.complete(j, rng_key=j, paths=10, cull_box=None)
    g = e.due(11, emitting=True)                  # 0 .. 3 merged
    e.ask(g, "count", ["a"], now=1.0)
    e.ask(g, "sums", ["a"], now=2.5)
    e.applied(g, deposits=40, now=3.0)
    assert e.gather_s == 2.0 and len(e.open) == 7
    assert e.drain_s() == 2.0 * (1 + 2)           # the next gather, then 6 more epochs: 2 gathers of 4


def _slow_sums(rounds: int, cluster_of):
    """A tamper that delivers every `epoch_sums` `rounds` rounds late: the
    gather's round trips, not the tracers, hold the render."""
    def tamper(sender, dest, msg):
        if msg.type != "epoch_sums":
            return [msg]
        cluster_of["c"].later(rounds, sender, dest, msg)
        return []
    return tamper


@pytest.mark.parametrize("growth", [8, 1])
def test_a_slow_gather_merges_epochs_and_a_tracer_lost_mid_merge_costs_no_photon(caustic, growth):
    """Behind a slow link, complete epochs merge into one gather (growth 8)
    or wait their turn (1, the control). A tracer killed while merged
    epochs are held discards them whole; every photon is applied once, the
    ledger re-traces the render and the image agrees with SPPM."""
    scene, ref = caustic
    provider = MemoryChunks(scene, uniform_tree(root_box(scene), (2, 2, 1)))
    holder = {}
    s = dataclasses.replace(_settings(), photon_batch=20_000)
    # Epochs of about 78k photons here (4,096 pixels' sums from 2 tracers).
    c = holder["c"] = InProcessCluster(provider, s, tracers=2, tracer_timeout_s=2.0, gather_at="tracers",
                                       tamper=_slow_sums(25, holder), batch_growth=growth)
    c.render(photons=PHOTONS)
    assert c.tracers["t1"].epochs.rows > 0
    c.kill("t1")
    c.run(photons=2 * PHOTONS)
    c.close()
    k, e = c.server.counters, c.server.epochs
    assert k["tracers_evicted"] == 1 and e.counters["epochs_discarded"] >= 1
    if growth > 1:
        assert e.counters["epochs_merged_most"] > 1
        assert e.counters["epoch_gathers"] < e.counters["epochs_applied"]
    else:
        assert e.counters["epochs_merged_most"] == 1
        assert e.counters["epoch_gathers"] == e.counters["epochs_applied"]
    assert k["photons_emitted"] - k["photons_discarded"] == k["photons_completed"] == k["photons_committed"]
    assert c.statistics.stats.photons_emitted == k["photons_committed"]
    assert all(t.epochs.rows == 0 for tid, t in c.tracers.items() if tid != "t1")
    assert ledger.check(provider, c.statistics.ledger.records) == []
    assert_same_within_noise(c.image(), ref[5][0], ref[9][0])


def test_an_answer_whose_sums_miss_the_rounds_rows_is_refused_not_taken():
    # The server adds answers into arrays of the round's rows without a
    # bounds check: a tracer's rows past them, or dense sums of another
    # length, must be refused with a line naming the field.
    from services import wire
    from services.server.epochs import Epochs
    e = Epochs(jobs_per_epoch=2)
    for j in (0, 1):
        e.made(j)
        e.complete(j, rng_key=j, paths=10, cull_box=None)
    ep = e.due(2, emitting=True)
    e.ask(ep, "sums", ["a", "b"], now=0.0, rows=5)

    def answer(**f):
        base = dict(epoch=ep.index, phase="sums", hits_version=0, deposits=3, chosen=0, flux=np.zeros(3))
        return wire.decode(wire.encode("epoch_sums", **base, **f))
    with pytest.raises(ValueError, match="'rows' reaches row 5, the round asked for 5"):
        e.answer("a", answer(rows=np.array([1, 5]), m=np.ones(2), phi=np.ones((2, 3))))
    with pytest.raises(ValueError, match="'m' has 4 rows, the round asked for 5"):
        e.answer("a", answer(m=np.ones(4), phi=np.ones((4, 3))))
    assert e.answer("a", answer(rows=np.array([0, 4]), m=np.ones(2), phi=np.ones((2, 3)))) is None
    done = e.answer("b", answer(m=np.ones(5), phi=np.ones((5, 3))))
    assert done is ep and total(done.sums, done.rows)["m"].tolist() == [2, 1, 1, 1, 2]


def test_a_stalled_gather_stops_emission_at_the_open_epochs_bound(caustic):
    """If no epoch's sums come back (a saturated link, a tracer slow to
    gather), the server stops making photon jobs OPEN_EPOCHS epochs past
    the next one to apply, so the deposits the tracers hold stay bounded;
    once the sums flow again the render goes on and counts every photon
    once. Control: the same cluster with the sums flowing makes jobs past
    that bound."""
    from services.server.epochs import OPEN_EPOCHS
    scene, _ = caustic
    stalled = {"on": True}

    def drop_sums(sender, dest, msg):
        return [] if stalled["on"] and msg.type == "epoch_sums" else [msg]

    def cluster(tamper):
        provider = MemoryChunks(scene, uniform_tree(root_box(scene), (2, 1, 1)))
        s = dataclasses.replace(_settings(), photon_batch=20_000)
        return provider, InProcessCluster(provider, s, tracers=2, gather_at="tracers", tamper=tamper)

    provider, c = cluster(drop_sums)
    try:
        for _ in range(600):
            c.round()
        e = c.server.epochs
        bound = e.first_id_after(e.next + OPEN_EPOCHS - 1)
        assert e.counters["epochs_applied"] == 0 and c.server.next_job <= bound
        assert e.of(c.server.next_job - 1) == e.next + OPEN_EPOCHS - 1     # it filled the room, no more
        held = sum(t.epochs.rows for t in c.tracers.values())
        assert held > 0
        stalled["on"] = False
        # The round under way waits for answers that were dropped: the
        # watchdog (all tracers idle) discards it and its epochs are made again.
        c.run(photons=c.server.counters["photons_emitted"] + 100_000)
        k = c.server.counters
        assert k["photons_emitted"] == k["photons_completed"] + k["photons_discarded"]
        assert k["photons_completed"] == k["photons_committed"] > 0
        assert ledger.check(provider, c.statistics.ledger.records) == []
    finally:
        c.close()
    _, free = cluster(None)
    try:
        for _ in range(600):
            free.round()
        assert free.server.epochs.counters["epochs_applied"] > 0
        assert free.server.epochs.of(free.server.next_job - 1) >= OPEN_EPOCHS
    finally:
        free.close()
