"""OSPPM in one process: chunked renders equal the unchunked render."""
from __future__ import annotations

import numpy as np
import pytest

from chunk_helpers import MemoryChunks, lattice_tree, root_box, skewed_tree, uniform_tree
from dosppm_core import builtin
from dosppm_core.osppm import OutOfCoreRenderer
from dosppm_core.render import Renderer, RenderSettings

ITERATIONS = 3


def _settings(**kw):
    return RenderSettings(seed=5, photons_per_iteration=40_000, **kw)


def _tiles(img, n=8):
    h, w = img.shape[:2]
    return img.reshape(n, h // n, n, w // n, 3).mean(axis=(1, 3))


@pytest.fixture(scope="module")
def caustic():
    """The glass and mirror spheres, 64x64; reference: the unchunked render."""
    scene = builtin.make("cornell-caustic")
    scene.camera.width = scene.camera.height = 64
    r = Renderer(scene, _settings())
    for _ in range(ITERATIONS):
        r.run_iteration()
    r.close()
    return scene, r.image(), r.progress()


def _osppm(scene, tree, memory=None, **kw):
    provider = MemoryChunks(scene, tree)
    o = OutOfCoreRenderer(provider, _settings(**kw), memory_bytes=memory)
    try:
        for _ in range(ITERATIONS):
            o.run_iteration()
        return o.image(), o.progress(), o.cache.counters, provider
    finally:
        o.close()


def _assert_equal_images(img, ref):
    assert img.shape == ref.shape
    # Equal up to floating-point noise: per pixel and per tile.
    assert np.allclose(img, ref, rtol=1e-4, atol=1e-6 * ref.max())
    assert np.allclose(_tiles(img), _tiles(ref), rtol=1e-5, atol=1e-7 * ref.max())


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
    scene, ref, _ = caustic
    tree = skewed_tree(root_box(scene), np.random.default_rng(2), 9)
    provider = MemoryChunks(scene, tree)
    memory = 1.2 * provider.chunk_memory.max()
    img, _, counters, provider = _osppm(scene, tree, memory=memory)
    _assert_equal_images(img, ref)
    assert counters.loads > tree.chunk_count      # evictions happened
    assert counters.loads + counters.wasted_prefetches == len(provider.loads)
    assert counters.wasted_prefetches == 0


def test_queued_batches_are_coalesced(caustic):
    """Client batching: each activation traces the chunk's whole queue as
    one batch, so batches never outnumber activations."""
    scene, _, _ = caustic
    tree = uniform_tree(root_box(scene), (2, 2, 2))
    _, _, counters, _ = _osppm(scene, tree)
    assert counters.traced_batches == counters.activations
    # Far fewer activations than batches arriving through portals.
    assert counters.activations < counters.portal_rays / 100


def test_memory_below_one_chunk_is_refused(caustic):
    scene, _, _ = caustic
    provider = MemoryChunks(scene, uniform_tree(root_box(scene), (2, 1, 1)))
    with pytest.raises(ValueError, match="below the largest chunk"):
        OutOfCoreRenderer(provider, _settings(), memory_bytes=provider.chunk_memory.max() / 2)
