"""Tracers make their own photons (issue 32, step 2): the server sends a
photon job as its id, rng key and count, and the tracer it picks makes
the photons with the library's call and sends them on like the rays
leaving a step (services/tracer/state.py `TracerState.emit`).

- The photons are bit for bit those the server made and sent before, in
  the same packages per start chunk (the same `located_photons` call);
  those that miss the scene end escaped, in the emission's results.
- Credit: the job's whole credit travels in the photon_job; the emission
  returns what its packages do not carry, so the job still completes
  exactly once, also when the tracer that emits serves none of the chunks
  its photons start in and forwards every one.
- The tracers of the lights' chunks emit, spread by their credit left, and
  a render's image is a function of its seed.
"""
from __future__ import annotations

import dataclasses
from fractions import Fraction

import numpy as np
import pytest

from dosppm_core.chunks.view import located_photons, start_chunks
from dosppm_core.jobs import ESCAPED, RayBatch
from services import ledger, wire
from services.inproc import InProcessCluster
from services.tracer.state import TracerState
from tests.helpers.chunks import MemoryChunks, root_box, uniform_tree
from tests.helpers.cluster import caustic_scene, settings
from tests.helpers.credit import credit_sum


def _over_the_wire(msg_type: str, fields: dict):
    return wire.decode([bytes(f) for f in wire.encode(msg_type, **fields)])


def _server_made(provider, seed, ids, keys, counts):
    """What the server sent before this change for one group of jobs: the
    photons of `located_photons`, routed job by job to their start chunks
    and concatenated per chunk in job order; and the count that missed."""
    header, tree = provider.header, provider.tree
    batch, chunk = located_photons(header, tree, seed, keys, counts, header.spawn_epsilon())
    batch.job[:] = np.repeat(ids, counts)
    parts, lost, ends = {}, 0, np.cumsum(counts)
    for a, b in zip((ends - counts).tolist(), ends.tolist()):
        routed, missed = start_chunks(tree, batch.slice(a, b), chunk=chunk[a:b])
        lost += missed
        for k, part in routed.items():
            parts.setdefault(k, []).append(part)
    return {k: RayBatch.concat(p) for k, p in parts.items()}, lost


def test_a_tracer_makes_bit_for_bit_the_photons_the_server_sent_and_returns_the_rest_of_the_credit():
    """Two chunks cut from the lower part of the scene: the photons start
    in both (tmin at the box they enter), and those heading past it miss
    the scene. Tracer a serves chunk 0 and queues its photons; chunk 1's
    go to tracer b in a portal package."""
    scene = caustic_scene()
    box = root_box(scene)
    box[1, 1] = 400.0                       # below the light (y 548.3)
    provider = MemoryChunks(scene, uniform_tree(box, (2, 1, 1)))
    a = TracerState("inproc://a", provider, 10, seed=7)
    try:
        a.set_peers(1, [["inproc://a"], ["inproc://b"]])
        ids, keys = np.array([40, 41, 42], np.int64), np.array([3, 17, 5], np.int64)
        counts = np.array([1000, 2500, 700], np.int64)
        cull_box = np.array([[-1.0, -2.0, -3.0], [600.0, 600.0, 600.0]])
        msg = _over_the_wire("photon_job", dict(job_ids=ids, rng_keys=keys, counts=counts, cull_box=cull_box,
                                                credit_job=ids, credit_exp=np.zeros(3, np.int64)))
        out = a.handle(msg)
        queued = [p for _kind, _e, p in a.schedule.pop(0).items()]
    finally:
        a.close()
    want, lost = _server_made(provider, 7, ids, keys, counts)
    assert set(want) == {0, 1} and 0 < lost < counts.sum() // 2
    results = [o.fields for o in out if o.type == "results"]
    portal = [o for o in out if o.type == "portal_rays"]
    assert len(results) == 1 and [o.dest for o in portal] == ["inproc://b"]
    got = {0: RayBatch.concat([p.batch for p in queued]), 1: portal[0].fields["batch"]}
    for k in (0, 1):
        for col, column in want[k].arrays().items():
            assert getattr(got[k], col).tobytes() == column.tobytes(), (k, col)
    assert portal[0].fields["kind"] == "photon" and np.array_equal(portal[0].fields["cull_box"], cull_box)
    assert all(np.array_equal(p.cull_box, cull_box) for p in queued)
    # The emission's results: every photon fed, those in a chunk went on,
    # the others escaped; no deposits. And the credit is all there, once.
    r = _over_the_wire("results", results[0])
    assert r.chunk is None and r.deposits is None and r.hits is None
    assert r.job_ids.tolist() == ids.tolist() and r.job_fed.tolist() == counts.tolist()
    assert int((r.job_fed - r.job_left).sum()) == lost == int(r.ends[ESCAPED]) == int(r.ends.sum())
    forwarded = (portal[0].fields["credit_job"], portal[0].fields["credit_exp"])
    total = credit_sum([(r.credit_job, r.credit_exp), forwarded, *[p.credit for p in queued]])
    assert total == {j: Fraction(1) for j in ids.tolist()}
    assert a.counters["photons_emitted"] == counts.sum()


def _tracers_emitted(c) -> dict:
    return {tid: t.counters["photons_emitted"] for tid, t in c.tracers.items()}


def _render(cells, tracers, seed=5):
    """(the chunks, a cluster of `tracers` on the caustic scene cut into `cells`), before its render."""
    scene = caustic_scene()
    provider = MemoryChunks(scene, uniform_tree(root_box(scene), cells))
    return provider, InProcessCluster(provider, dataclasses.replace(settings(seed), photon_batch=20_000),
                                      tracers=tracers)


def test_photons_emitted_for_another_tracers_chunk_are_forwarded_and_each_job_completes_once(monkeypatch):
    """The light lies in chunk 1 (the upper half), which t1 serves; t0,
    serving only chunk 0, is made the only emitter. Every photon it makes
    goes to t1 in portal packages, and every job completes once, with all
    its credit and every path ended, as the ledger's re-trace confirms."""
    provider, c = _render((1, 2, 1), 2)
    assert c.server.light_chunks == [1] and c.server.owners == [["t0"], ["t1"]]
    monkeypatch.setattr(c.server, "_emitters", lambda: [c.server.tracers["t0"]])
    completed = []
    complete = c.server._complete
    monkeypatch.setattr(c.server, "_complete", lambda j, job: (completed.append(j), complete(j, job)))
    sent = []
    post = c._post

    def watch(sender, outs):
        outs = list(outs)
        sent.extend(j for o in outs if o.type == "photon_job" for j in o.fields["job_ids"].tolist())
        post(sender, outs)
    monkeypatch.setattr(c, "_post", watch)
    try:
        c.run(photons=40_000)
    finally:
        c.close()
    k = c.server.counters
    t0, t1 = c.tracers["t0"].counters, c.tracers["t1"].counters
    assert _tracers_emitted(c) == {"t0": k["photons_emitted"], "t1": 0}
    assert t0["portal_rays_out"] >= k["photons_emitted"] and t1["portal_rays_in"] >= k["photons_emitted"]
    photon_jobs = [j for j in completed if j in set(sent)]
    assert sorted(photon_jobs) == sorted(set(sent)) and len(photon_jobs) == len(set(sent)) == len(sent)
    assert k["photon_jobs_completed"] == len(sent) and k["over_credited_jobs"] == 0
    assert k["photons_emitted"] == k["photons_completed"] == k["photons_committed"] == k["photon_paths_ended"]
    assert k["stale_paths"] == 0 and k["deposits_late"] == 0 and not c.server.jobs
    assert ledger.check(provider, c.statistics.ledger.records) == []


@pytest.mark.parametrize("cells, emitters", [((1, 2, 1), {"t1"}), ((1, 1, 1), {"t0", "t1"})],
                         ids=["light in t1's chunk", "one shared chunk"])
def test_the_tracers_of_the_lights_chunks_emit_spread_by_their_credit(cells, emitters):
    _, c = _render(cells, 2)
    try:
        c.run(photons=40_000)
    finally:
        c.close()
    emitted = _tracers_emitted(c)
    assert {tid for tid, n in emitted.items() if n} == emitters
    assert sum(emitted.values()) == c.server.counters["photons_emitted"]
    if len(emitters) > 1:       # the least loaded first: neither makes more than twice the other's
        assert max(emitted.values()) <= 2 * min(emitted.values())


def test_a_render_is_a_function_of_its_seed_bit_for_bit():
    """The in-process cluster runs on its own clock: the same seed gives
    the same image, bit for bit; another seed another image."""
    images = []
    for seed in (5, 5, 9):
        _, c = _render((2, 1, 1), 2, seed=seed)
        try:
            c.run(photons=40_000)
        finally:
            c.close()
        images.append(np.asarray(c.image()))
    assert images[0].tobytes() == images[1].tobytes()
    assert images[0].tobytes() != images[2].tobytes()


def test_a_tracer_without_the_seed_refuses_photon_jobs():
    scene = caustic_scene()
    provider = MemoryChunks(scene, uniform_tree(root_box(scene), (1, 1, 1)))
    t = TracerState("inproc://t", provider, 10)
    try:
        one = np.ones(1, np.int64)
        with pytest.raises(ValueError, match="seed"):
            t.emit(one, one, one, np.zeros((2, 3)), (one, 0 * one))
    finally:
        t.close()
