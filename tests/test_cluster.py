"""The distributed service's logic, without sockets: a server and tracers
exchanging real wire messages in one process (`services.inproc`).

- The image equals single-process SPPM within noise, per tile, for c > n,
  c = n and c < n, including eight chunks meeting inside the glass sphere.
- Exact accounting: photons emitted = photons completed = photons applied
  to the statistics; no path is counted twice or left over; every eye
  iteration completes with exactly the hit points of the same iteration in
  single-process SPPM.
- Portal traffic between tracers really happens when c > 1.
"""
from __future__ import annotations

import dataclasses

import pytest

from dosppm_core.modes.sppm import Renderer
from services.inproc import InProcessCluster
from tests.helpers.chunks import MemoryChunks, lattice_tree, root_box, uniform_tree
from tests.helpers.cluster import (
    ITERATIONS,
    assert_same_within_noise,
    caustic_reference,
    caustic_scene,
    settings,
)

PHOTONS = 240_000
_assert_same_within_noise = assert_same_within_noise
_settings = settings


@pytest.fixture(scope="module")
def caustic():
    return caustic_scene(), caustic_reference()


def _cluster(scene, tree, tracers, **kw):
    c = InProcessCluster(MemoryChunks(scene, tree), _settings(), tracers=tracers, **kw)
    try:
        c.run(photons=PHOTONS)
    finally:
        c.close()
    return c


LAYOUTS = {
    "c=1 n=2 (shared chunk)": (lambda s: uniform_tree(root_box(s), (1, 1, 1)), 2),
    "c=2 n=2": (lambda s: uniform_tree(root_box(s), (2, 1, 1)), 2),
    "c=8 n=3, chunks meet in the glass": (lambda s: lattice_tree(root_box(s), [[c] for c in _glass_centre(s)]), 3),
}


def _glass_centre(scene):
    glass = scene.materials.names.index("glass")
    v = scene.vertices[scene.triangles[scene.tri_material == glass]].reshape(-1, 3)
    return (v.min(0) + v.max(0)) / 2


@pytest.mark.parametrize("layout", list(LAYOUTS))
def test_cluster_renders_the_single_process_image(caustic, layout):
    scene, ref = caustic
    make_tree, n = LAYOUTS[layout]
    tree = make_tree(scene)
    c = _cluster(scene, tree, n)
    s = c.server
    _assert_same_within_noise(c.image(), ref[5][0], ref[9][0])
    # Exact accounting: every photon emitted was completed and applied once.
    k = s.counters
    assert k["photons_emitted"] >= PHOTONS
    assert k["photons_emitted"] == k["photons_completed"] == k["photons_committed"]
    assert c.statistics.stats.photons_emitted == k["photons_emitted"]
    assert k["over_credited_jobs"] == 0 and k["stale_paths"] == 0 and not s.jobs
    assert c.statistics.deposits_applied == k["deposits_received"]
    # Hit-point iterations complete exactly: iteration i has the hit points
    # of single-process SPPM's iteration i (eye rays depend only on it).
    assert s.eye_completed >= 1
    per_iteration = ref[5][1].hit_points / ITERATIONS
    assert k["hit_points"] == pytest.approx(s.eye_completed * per_iteration, rel=0.02)
    # Tracer-to-tracer portal traffic, and only where there are portals.
    out = sum(t.counters["portal_rays_out"] for t in c.tracers.values())
    got = sum(t.counters["portal_rays_in"] for t in c.tracers.values())
    assert out == got
    assert (out > 0) == (tree.chunk_count > 1)
    # Work was shared: every tracer traced.
    assert all(t.counters["rays_traced"] > 0 for t in c.tracers.values())


def test_eye_iterations_match_single_process_hit_points_exactly(caustic):
    """Eye iteration i traces the same rays as SPPM's iteration i, so the
    number of hit points per iteration is equal, not just close."""
    scene, _ = caustic
    tree = uniform_tree(root_box(scene), (2, 2, 1))
    c = InProcessCluster(MemoryChunks(scene, tree), _settings(), tracers=2)
    per_iteration = []
    seen = 0
    for _ in range(2000):
        c.round()
        if c.server.eye_completed > len(per_iteration):
            per_iteration.append(c.server.counters["hit_points"] - seen)
            seen = c.server.counters["hit_points"]
        if len(per_iteration) >= 3:
            break
    c.close()
    r = Renderer(scene, _settings())
    expected = []
    for _ in range(3):
        before = r.sppm.hit_point_total
        r.run_iteration()
        expected.append(r.sppm.hit_point_total - before)
    r.close()
    assert per_iteration == expected


def test_memory_limited_tracer_works_through_its_chunks(caustic):
    """c = 8, n = 2 with room for one chunk per tracer: each tracer loads
    its four chunks in turn, and the render is still right."""
    scene, ref = caustic
    provider = MemoryChunks(scene, uniform_tree(root_box(scene), (2, 2, 2)))
    c = InProcessCluster(provider, _settings(), tracers=2, memory_bytes=provider.chunk_memory.max())
    c.run(photons=PHOTONS)
    c.close()
    assert all(len(t.cache.resident) <= 1 for t in c.tracers.values())
    assert sum(t.cache.counters.loads for t in c.tracers.values()) > 8
    _assert_same_within_noise(c.image(), ref[5][0], ref[9][0])
    k = c.server.counters
    assert k["photons_emitted"] == k["photons_committed"]


def test_a_tracer_joining_mid_render_gets_chunks_and_work(caustic):
    """c = 4: two tracers start; a third joins mid-render, is given chunks
    by the new round-robin table, and packages already queued for chunks
    that moved are passed on to it. Nothing is lost or counted twice."""
    scene, ref = caustic
    provider = MemoryChunks(scene, uniform_tree(root_box(scene), (2, 2, 1)))
    c = InProcessCluster(provider, _settings(), tracers=2)
    c.render(photons=PHOTONS // 2)
    new = c.add_tracer()
    assert c.tracers[new].chunks == [2]
    assert all(t.table_version == c.server.table_version for t in c.tracers.values())
    c.render(photons=PHOTONS)
    c.drain()
    c.close()
    assert c.tracers[new].counters["rays_traced"] > 0
    k = c.server.counters
    assert k["photons_emitted"] == k["photons_completed"] == k["photons_committed"]
    assert k["over_credited_jobs"] == 0 and k["stale_paths"] == 0
    _assert_same_within_noise(c.image(), ref[5][0], ref[9][0])


def test_tracers_cull_deposits_outside_the_box_they_were_sent():
    """Photon culling (§4.3): a tracer drops deposits outside the job's box
    before sending, and coalesced packages use the union of their boxes."""
    import numpy as np

    from dosppm_core.trace import emit_photon_job
    from services.tracer.state import TracerState, union_box
    scene = caustic_scene()
    provider = MemoryChunks(scene, uniform_tree(root_box(scene), (1, 1, 1)))
    a, b = np.array([[0, 0, 0], [1, 2, 3]], float), np.array([[-1, 1, 1], [0.5, 5, 2]], float)
    assert np.array_equal(union_box([a, b]), [[-1, 0, 0], [1, 5, 3]])
    lo, hi = scene.bounds()
    floor_only = np.array([lo - 1, [hi[0] + 1, lo[1] + 1.0, hi[2] + 1]])   # a slab at the floor
    counts = {}
    for name, box in (("all", np.array([lo - 1, hi + 1])), ("floor", floor_only)):
        t = TracerState("inproc://t", provider, 10)
        t.set_peers(1, [["inproc://t"]])
        t.receive("photon", 0, emit_photon_job(provider.header, 1, 0, 20_000, 1e-6 * scene.diagonal()),
                  cull_box=box)
        out = []
        while t.has_work():
            out += t.step()
        results = [o.fields for o in out if o.type == "results"]
        dep = np.concatenate([r["deposits"].position for r in results])
        counts[name] = (len(dep), sum(r["culled"] for r in results))
        assert (dep >= box[0]).all() and (dep <= box[1]).all()
        t.close()
    assert counts["all"][1] == 0 and counts["floor"][1] > 0
    assert counts["floor"][0] + counts["floor"][1] == counts["all"][0]


def test_a_killed_tracer_loses_no_photon_and_counts_none_twice(caustic):
    """c = 4 over three tracers; one stops dead mid-render. The server
    notices by its silence, gives its chunks to the others, discards every
    job in flight whole and re-emits it with the same photons; the render
    completes with nothing lost or counted twice, and the image agrees with
    SPPM within noise."""
    scene, ref = caustic
    provider = MemoryChunks(scene, uniform_tree(root_box(scene), (2, 2, 1)))
    c = InProcessCluster(provider, _settings(), tracers=3, tracer_timeout_s=2.0)
    c.render(photons=PHOTONS // 3)
    c.kill("t1")
    c.render(photons=PHOTONS)
    c.drain()
    c.close()
    s, k = c.server, c.server.counters
    assert k["tracers_evicted"] == 1 and "t1" not in s.tracers
    assert all(o and "t1" not in o for o in s.owners)
    assert k["jobs_discarded"] > 0 and k["photons_discarded"] > 0
    # Exactly once: what was emitted and not discarded was completed and
    # applied; discarded jobs' deposits never reached the statistics.
    assert k["photons_emitted"] - k["photons_discarded"] == k["photons_completed"] == k["photons_committed"]
    assert c.statistics.stats.photons_emitted == k["photons_committed"]
    assert k["over_credited_jobs"] == 0
    _assert_same_within_noise(c.image(), ref[5][0], ref[9][0])


class _Watched(InProcessCluster):
    """Records the most eye iterations the server had in flight at once."""
    most_eye_in_flight = 0

    def round(self) -> None:
        super().round()
        self.most_eye_in_flight = max(self.most_eye_in_flight, len(self.server.eyes))


def _overlapped(scene, in_flight: int, seed: int):
    """A render with an eye iteration started every 4,096 photons, so
    iterations overlap when the server lets them."""
    provider = MemoryChunks(scene, uniform_tree(root_box(scene), (2, 1, 1)))
    c = _Watched(provider, dataclasses.replace(_settings(seed), photons_per_iteration=4096), tracers=2)
    c.server.eye_in_flight = in_flight
    try:
        c.run(photons=PHOTONS)
    finally:
        c.close()
    return provider, c


def test_overlapping_eye_iterations_converge_to_the_sequential_image(caustic):
    """Issue 31: eye iterations traced at once (iteration i + 1's hit points
    while photons are applied to iteration i's) give the image of one at a
    time within noise (another seed's); each installed iteration has
    exactly its hit points, and the ledger re-traces the render exactly."""
    from services import ledger
    scene, ref = caustic
    _, one = _overlapped(scene, 1, seed=5)
    _, noise = _overlapped(scene, 1, seed=9)
    provider, four = _overlapped(scene, 4, seed=5)
    assert one.most_eye_in_flight == 1 and four.most_eye_in_flight >= 2
    _assert_same_within_noise(four.image(), one.image(), noise.image())
    per_iteration = ref[5][1].hit_points / ITERATIONS
    for c in (one, four):
        k = c.server.counters
        assert k["photons_emitted"] == k["photons_completed"] == k["photons_committed"]
        assert k["hit_points"] == pytest.approx(c.server.eye_completed * per_iteration, rel=0.02)
    assert four.server.eye_completed > ITERATIONS
    assert ledger.check(provider, four.statistics.ledger.records) == []
