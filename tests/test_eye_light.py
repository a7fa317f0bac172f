"""The light eye paths saw, held at the tracers and collected in rounds
(issue 32; services/tracer/light.py and services/server/eye_light.py):
summed per pixel exactly, each iteration applied once or never, and a
render's image and counts the same as when it travelled with the results."""
from __future__ import annotations

import dataclasses

import numpy as np

from services import wire
from services.inproc import InProcessCluster
from services.server.eye_light import LightRounds, summed
from services.tracer.light import LightHold
from tests.helpers.chunks import MemoryChunks, root_box, uniform_tree
from tests.helpers.cluster import assert_same_within_noise, caustic_reference, caustic_scene, settings


def _light(rng, n, pixels=50):
    return rng.integers(0, pixels, n).astype(np.int32), rng.random((n, 3)).astype(np.float32)


def test_a_reply_sums_the_asked_iterations_per_pixel_and_forgets_them():
    rng = np.random.default_rng(3)
    hold, truth = LightHold(), {}
    for e in (0, 1, 2, 4):
        for _ in range(3):
            p, c = _light(rng, 40)
            hold.add(e, p, c)
            truth.setdefault(e, []).append((p, c))
    out = wire.decode([bytes(f) for f in wire.encode("eye_light", **hold.reply(7, np.array([1, 2])))])
    want = np.zeros((50, 3))
    for p, c in truth[1] + truth[2]:
        np.add.at(want, p, c.astype(np.float64))
    got = np.zeros((50, 3))
    got[out.pixels] = out.rgb
    assert out.round == 7 and np.all(np.diff(out.pixels) > 0)
    np.testing.assert_allclose(got, want, rtol=1e-6)
    # Iteration 0 was passed over (the server discarded it): dropped; 4 is still held.
    assert sorted(hold.held) == [4] and hold.counters["light_iterations_dropped"] == 1
    assert len(hold.reply(8, np.array([1, 2]))["pixels"]) == 0      # asked twice: nothing twice


def test_rounds_wait_for_a_batch_then_every_answer_and_a_loss_discards_what_is_not_applied():
    r = LightRounds(batch=3)
    for e in range(2):
        r.complete(e)
    assert r.start({"a", "b"}, 0.0, final=False) is None          # 2 of 3
    r.complete(2)
    first = r.start({"a", "b"}, 1.0, final=False)
    assert first.iterations == [0, 1, 2] and r.start({"a", "b"}, 1.0, final=True) is None   # one at a time

    def answer(tid, round_, pixels):
        return r.answer(tid, wire.Message("eye_light", dict(round=round_, pixels=np.array(pixels, np.int32),
                                                               rgb=np.ones((len(pixels), 3), np.float32))))
    assert answer("a", 0, [1, 2]) is None
    assert answer("a", 0, [1, 2]) is None                          # a repeat: not counted twice
    assert answer("c", 0, [3]) is None                             # not asked
    done = answer("b", 0, [2, 5])
    assert done is first
    np.testing.assert_array_equal(summed(done.parts, 6)[:, 0], [0, 1, 2, 0, 0, 1])
    r.complete(3)
    assert r.start({"a"}, 2.0, final=True).iterations == [3]      # draining: whatever is due
    r.complete(4)
    r.discard()                                                    # a tracer lost: 3 (asked) and 4 (due)
    assert r.drained and r.counters["eye_iterations_light_discarded"] == 2
    assert answer("a", 1, [0]) is None                             # the discarded round's late answer


def test_a_render_sends_no_light_with_its_results_and_counts_every_iteration_once():
    scene, ref = caustic_scene(), caustic_reference()
    provider = MemoryChunks(scene, uniform_tree(root_box(scene), (2, 1, 1)))
    with_light = []

    def watch(sender, dest, msg):
        if msg.type == "results" and msg.emitted_pixels is not None:
            with_light.append(msg)
        return [msg]

    c = InProcessCluster(provider, dataclasses.replace(settings(5), photon_batch=60_000), tracers=2,
                         gather_at="tracers", hit_point_stride=2, tamper=watch)
    try:
        c.run(photons=240_000)
    finally:
        c.close()
    assert not with_light
    assert c.server.light.counters["light_rounds"] >= 2
    assert c.statistics.stats.eye_iterations == c.server.eye_completed >= 4
    assert all(not t.light.held for t in c.tracers.values())
    assert_same_within_noise(c.image(), ref[5][0], ref[9][0])
