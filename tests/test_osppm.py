"""OSPPM in one process: chunked renders equal the unchunked render."""
from __future__ import annotations

import numpy as np
import pytest

from dosppm_core.modes.osppm import OutOfCoreRenderer
from dosppm_core.modes.sppm import Renderer
from dosppm_core.settings import RenderSettings
from tests.helpers.chunks import MemoryChunks, lattice_tree, root_box, skewed_tree, uniform_tree
from tests.helpers.cli import run_dosppm
from tests.helpers.scenes import small_scene

ITERATIONS = 3


def _settings(**kw):
    return RenderSettings(seed=5, photons_per_iteration=40_000, **kw)


def _tiles(img, n=8):
    h, w = img.shape[:2]
    return img.reshape(n, h // n, n, w // n, 3).mean(axis=(1, 3))


@pytest.fixture(scope="module")
def caustic():
    """The glass and mirror spheres, 64x64; reference: the unchunked render."""
    scene = small_scene("cornell-caustic", 64)
    r = Renderer(scene, _settings())
    for _ in range(ITERATIONS):
        r.run_iteration()
    r.close()
    return scene, r.image(), r.progress()


def _osppm(scene, tree, memory=None, **kw):
    provider = MemoryChunks(scene, tree)
    o = OutOfCoreRenderer(provider, _settings(**kw), memory_bytes=memory, pipelined=False)
    try:
        for _ in range(ITERATIONS):
            o.run_iteration()
        return o.image(), o.progress(), o.cache.counters, provider
    finally:
        o.close()


def _assert_equal_images(img, ref):
    """Equal up to floating-point noise, per pixel and per 8x8 tile. Noise:
    each chunk's BVH may find a hit a float32 ulp apart from the whole
    scene's, which can move a photon across a radius boundary, so a few
    pixels may differ by one photon's share; nothing else may differ."""
    assert img.shape == ref.shape
    rel = np.abs(img - ref) / np.maximum(ref, 1e-6 * ref.max())
    assert np.mean(rel > 1e-4) < 0.02, f"{np.mean(rel > 1e-4):.2%} of pixels differ"
    assert rel.max() < 0.01, f"a pixel differs by {rel.max():.2%}"
    tiles_ref = _tiles(ref)
    assert np.allclose(_tiles(img), tiles_ref, rtol=1e-3, atol=1e-6 * tiles_ref.max())


def _glass_centre(scene):
    glass = scene.materials.names.index("glass")
    v = scene.vertices[scene.triangles[scene.tri_material == glass]].reshape(-1, 3)
    return (v.min(0) + v.max(0)) / 2


@pytest.mark.parametrize("layout", ["one", "eight-through-glass", "27"])
def test_chunked_equals_unchunked(caustic, layout):
    """c = 1, c = 8 with all eight chunks meeting inside the glass sphere
    (the seamless caustic of the paper's Figure 14), and c = 27."""
    scene, ref, ref_progress = caustic
    box = root_box(scene)
    tree = {"one": lambda: uniform_tree(box, (1, 1, 1)),
            "eight-through-glass": lambda: lattice_tree(box, [[c] for c in _glass_centre(scene)]),
            "27": lambda: uniform_tree(box, (3, 3, 3))}[layout]()
    img, progress, counters, _ = _osppm(scene, tree)
    _assert_equal_images(img, ref)
    assert progress.photons_emitted == ref_progress.photons_emitted
    assert progress.hit_points == ref_progress.hit_points
    if tree.chunk_count > 1:
        assert counters.portal_rays > 0


def test_t_junction_tree_and_tight_memory_give_the_same_image(caustic):
    """Nine chunks with T-junctions and room for little more than the largest: chunks
    are evicted and reloaded, and nothing changes."""
    scene = caustic[0]
    tree = skewed_tree(root_box(scene), np.random.default_rng(2), 9)
    provider = MemoryChunks(scene, tree)
    memory = 1.2 * provider.chunk_memory.max()
    # No light cache on either side: in this little memory it would be
    # smaller than the unchunked render's, and would overflow.
    r = Renderer(scene, _settings(light_cache=0))
    for _ in range(ITERATIONS):
        r.run_iteration()
    r.close()
    img, _, counters, provider = _osppm(scene, tree, memory=memory, light_cache=0)
    _assert_equal_images(img, r.image())
    assert counters.loads > tree.chunk_count      # evictions happened
    assert counters.loads + counters.wasted_prefetches == len(provider.loads)
    assert counters.wasted_prefetches == 0


def test_queued_batches_are_coalesced(caustic):
    """Client batching: each activation traces the chunk's whole eye queue
    and whole photon queue as one batch each."""
    scene, _, _ = caustic
    tree = uniform_tree(root_box(scene), (2, 2, 2))
    _, _, counters, _ = _osppm(scene, tree)
    assert counters.traced_batches <= 2 * counters.activations
    # Far fewer activations than batches arriving through portals.
    assert counters.activations < counters.portal_rays / 100


def test_memory_below_one_chunk_is_refused(caustic):
    scene, _, _ = caustic
    provider = MemoryChunks(scene, uniform_tree(root_box(scene), (2, 1, 1)))
    with pytest.raises(ValueError, match="below the largest chunk"):
        OutOfCoreRenderer(provider, _settings(), memory_bytes=provider.chunk_memory.max() / 2)


def test_store_with_exact_insertion_renders_the_unchunked_image(caustic, chunk_store):
    """The real pipeline: subdivide (exact triangle-box insertion) into
    8 chunks, open the store, render OSPPM from it."""
    scene, ref, _ = caustic
    store = chunk_store(scene, chunks=8)
    assert store.chunk_count == 8
    assert store.chunk_triangles.sum() > scene.triangle_count   # straddlers duplicated
    o = OutOfCoreRenderer(store, _settings(), pipelined=False)
    try:
        for _ in range(ITERATIONS):
            o.run_iteration()
        _assert_equal_images(o.image(), ref)
        assert o.cache.counters.portal_rays > 0
    finally:
        o.close()


def test_cli_renders_chunked_and_reuses_the_store(tmp_path):
    from dosppm_core.film import read_exr

    def run(*extra):
        return run_dosppm("render", "cornell-box", "--iterations", "2", "--width", "32", "--height", "32",
                          "--store-cache", tmp_path / "cache", "--quiet", *extra, cwd=tmp_path, timeout=600)
    a = run("--mode", "osppm", "--chunks", "4", "--schedule", "drained", "--out", str(tmp_path / "a.exr"))
    assert a.returncode == 0, a.stderr
    b = run("--mode", "sppm", "--out", str(tmp_path / "b.exr"))
    assert b.returncode == 0, b.stderr
    img_a, img_b = read_exr(str(tmp_path / "a.exr"))[0], read_exr(str(tmp_path / "b.exr"))[0]
    _assert_equal_images(img_a, img_b)
    assert len(list((tmp_path / "cache").iterdir())) == 1
    c = run("--mode", "osppm", "--chunks", "4", "--out", str(tmp_path / "c.exr"))   # the store is reused
    assert c.returncode == 0 and len(list((tmp_path / "cache").iterdir())) == 1
    bad = run("--mode", "osppm", "--budget", "12parsecs")
    assert bad.returncode == 2 and bad.stderr.count("\n") == 1 and "--budget" in bad.stderr


def test_pipelined_schedule_converges_to_the_same_image(caustic):
    """§3.3: one sweep per iteration, rays left in portal queues carried
    into the next. Not bit-equal (the photons of an iteration differ) but
    the same estimate: after finish() no ray is queued, every emitted
    photon was traced, and the image agrees with the drained one within
    noise."""
    scene, _, _ = caustic
    tree = uniform_tree(root_box(scene), (2, 2, 2))
    results = {}
    for pipelined in (False, True):
        o = OutOfCoreRenderer(MemoryChunks(scene, tree), _settings(), pipelined=pipelined)
        try:
            o.run_iteration()      # the first drains its eye paths: the first hit points
            first = o.cache.counters.activations
            for _ in range(7):
                o.run_iteration()
            if pipelined:
                assert o.rays_queued > 0     # work really was carried over
                # then one sweep per iteration: each chunk activated at most once
                assert o.cache.counters.activations - first <= 7 * tree.chunk_count
            drain = []
            o.finish(report=lambda rays, sweeps: drain.append((rays, sweeps)))
            assert o.rays_queued == 0
            # The drain reports each sweep, down to no ray queued.
            assert [s for _, s in drain] == list(range(1, len(drain) + 1))
            assert bool(drain) == pipelined and (not drain or drain[-1][0] == 0)
            results[pipelined] = (o.image(), o.progress())
            # Every path ended exactly once: each photon emitted and each
            # eye path of every eye iteration (a pipelined eye iteration,
            # shadow rays included, spans sweeps, so it completes fewer).
            n_pix = scene.camera.width * scene.camera.height
            assert sum(o.progress().path_ends.values()) == \
                o.progress().photons_emitted + n_pix * o.eye_iterations
        finally:
            o.close()
    (a, pa), (b, pb) = results[False], results[True]
    assert pa.photons_emitted == pb.photons_emitted
    ta, tb = _tiles(a), _tiles(b)
    rel = np.sum((ta - tb) ** 2) / np.sum(ta ** 2)
    assert rel < 0.01, f"tile relMSE {rel:.4f}"
    assert abs(a.mean() / b.mean() - 1) < 0.03


def test_a_pipelined_iteration_applies_its_deposits_a_batch_at_a_time(caustic):
    """Issue 17: a paced iteration's deposits used to wait for its end, all
    of them (491 MiB against a 400 MiB limit at 119 chunks). Now each
    chunk's deposits go to the statistics as they are made, a batch once
    `photon_batch` wait: every batch but an iteration's last is exactly
    one batch, nothing waits past it, and every deposit is applied once."""
    scene, _, _ = caustic
    batch = 3_000
    o = OutOfCoreRenderer(MemoryChunks(scene, uniform_tree(root_box(scene), (2, 2, 2))),
                          _settings(photon_batch=batch), pipelined=True)
    sizes, waiting, during = [], [], []
    apply, add = o.sppm.apply_photon_batch, o.sppm.add_photons

    def spy_apply(deposits, emitted):
        sizes.append(sum(len(p) for p in (deposits if isinstance(deposits, list) else [deposits])))
        during.append(o.cache.counters.activations)      # how far the sweep had got
        apply(deposits, emitted)

    def spy_add(deposits, emitted):
        add(deposits, emitted)
        waiting.append(o.sppm._pending_rows)
    o.sppm.apply_photon_batch, o.sppm.add_photons = spy_apply, spy_add
    try:
        o.run_iteration()
        per_iteration, sweep_points = [], []
        for _ in range(3):
            before = len(sizes)
            o.run_iteration()
            per_iteration.append(sizes[before:])
            sweep_points.append(set(during[before:]))
        o.finish()
    finally:
        o.close()
    assert all(len(p) > 2 for p in per_iteration), "an iteration's deposits came as one batch"
    assert all(len(p) > 1 for p in sweep_points), "the deposits waited for the end of the sweep"
    assert all(s == batch for p in per_iteration for s in p[:-1])
    assert max(sizes) <= batch and max(waiting) < batch
    assert sum(sizes) == o.sppm.deposits_applied > 0


def test_a_chunk_queue_is_traced_in_steps_with_the_same_image(caustic, monkeypatch):
    """A photon iteration starts all in the chunks with lights; their queues
    are traced TRACE_STEP_RAYS at a time (rays are independent), not in one
    concatenation three times the queue's size, and the image is unchanged."""
    from dosppm_core.modes import osppm
    scene, ref, _ = caustic
    sizes = []
    trace = osppm.trace_photons_in_chunk

    def spy(view, batch, *args):
        sizes.append(len(batch))
        return trace(view, batch, *args)
    monkeypatch.setattr(osppm, "TRACE_STEP_RAYS", 4096)
    monkeypatch.setattr(osppm, "trace_photons_in_chunk", spy)
    img, _, _, _ = _osppm(scene, uniform_tree(root_box(scene), (2, 2, 2)))
    _assert_equal_images(img, ref)
    jobs = _settings().photons_per_job
    assert max(sizes) <= 4096 + jobs and sum(s > 4096 - jobs for s in sizes) > 3
