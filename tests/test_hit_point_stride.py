"""Eye iterations that install no hit points (issue 32): where eye
iterations run beside the photons, a set of hit points is only gathered at
by the statistics updates made while it is installed, so one iteration in
`hit_point_stride` installs its set; the others count only the emission
and direct light their paths saw. Tracers send no hit points for them."""
from __future__ import annotations

import dataclasses

import pytest

from dosppm_core.sppm.iteration import hit_point_stride, keeps_hit_points
from services import ledger
from services.inproc import InProcessCluster
from tests.helpers.chunks import MemoryChunks, root_box, uniform_tree
from tests.helpers.cluster import assert_same_within_noise, caustic_reference, caustic_scene, settings

PHOTONS = 240_000       # an eye iteration each 40,000 photons emitted


def test_one_set_per_update_and_the_first_iteration_always_installs():
    # A 256 x 256 image (98,304 photons an iteration) and 1M-photon updates.
    assert hit_point_stride(1_000_000, 98_304) == 10
    assert hit_point_stride(60_000, 98_304) == 1          # updates smaller than an iteration: every one
    assert [i for i in range(10) if keeps_hit_points(i, 3)] == [0, 3, 6, 9]
    assert all(keeps_hit_points(i, 1) for i in range(5))


@pytest.mark.parametrize("gather_at", ["tracers", "server"])
def test_only_every_strideth_iteration_sends_and_installs_hit_points(gather_at):
    """Stride 3 over five or six eye iterations: results carry hit points of
    iterations 0 and 3 only, the statistics install those two sets and
    count every iteration' emission, every photon is applied once (the
    ledger re-traces the render, emission-only iterations included), and
    the image agrees with single-process SPPM within noise."""
    scene, ref = caustic_scene(), caustic_reference()
    provider = MemoryChunks(scene, uniform_tree(root_box(scene), (2, 1, 1)))
    sent = []      # (eye iteration, hit points sent, hit points made) of each eye results message

    def watch(sender, dest, msg):
        if msg.type == "results" and msg.eye_iteration is not None and msg.hits is not None:
            sent.append((msg.eye_iteration, len(msg.hits), msg.hit_points_made))
        return [msg]

    c = InProcessCluster(provider, dataclasses.replace(settings(5), photon_batch=60_000), tracers=2,
                         gather_at=gather_at, hit_point_stride=3, tamper=watch)
    try:
        c.run(photons=PHOTONS)
    finally:
        c.close()
    done = c.server.eye_completed
    assert done >= 4          # iterations 0 and 3 install
    assert {e for e, n, _ in sent if n} == {i for i in range(done) if i % 3 == 0}
    assert sum(made for e, _, made in sent if e % 3) > 0          # made and counted, not sent
    assert all(n in (0, made) for _, n, made in sent)
    stats = c.statistics.stats
    assert stats.eye_iterations == done
    assert c.statistics.sppm.hit_point_total == sum(n for _, n, _ in sent)
    assert c.server.counters["hit_points"] == sum(made for _, _, made in sent)
    assert ledger.check(provider, c.statistics.ledger.records) == []
    assert_same_within_noise(c.image(), ref[5][0], ref[9][0])


def test_a_lost_first_iteration_is_restarted_at_one_that_installs():
    """Photons wait for a set of hit points. A tracer lost while the first
    eye iteration is in flight discards it, and the next index (1) would
    install none at stride 3: the server starts iteration 3 instead, and
    the render goes on (without this it waited for ever)."""
    scene = caustic_scene()
    provider = MemoryChunks(scene, uniform_tree(root_box(scene), (2, 1, 1)))
    c = InProcessCluster(provider, dataclasses.replace(settings(5), photon_batch=60_000), tracers=3,
                         tracer_timeout_s=2.0, gather_at="tracers", hit_point_stride=3)
    try:
        c.kill("t2")                     # before anything was traced: iteration 0 cannot complete
        c.run(photons=80_000)
    finally:
        c.close()
    k = c.server.counters
    assert k["tracers_evicted"] == 1 and k["eye_iterations_restarted"] == 1
    kept = [r["eye_iteration"] for r in c.statistics.ledger.records if r["kind"] == "hits" and r["kept"]]
    assert kept[0] == 3
    assert k["photons_committed"] >= 80_000 and c.statistics.stats.photons_emitted == k["photons_committed"]
