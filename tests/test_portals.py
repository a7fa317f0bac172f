"""Portal traversal is exact: chunk by chunk, a ray finds the first hit it
finds in the unchunked scene (issue 3, ray-level equality)."""
from __future__ import annotations

import numpy as np
import pytest

from dosppm_core.accel import Accelerator
from dosppm_core.chunks.portals import enter, exit_chunk
from dosppm_core.chunks.tree import ChunkTree
from dosppm_core.chunks.view import ChunkView
from dosppm_core.jobs import RayBatch
from dosppm_core.scene import builtin
from tests.helpers.chunks import bbox_chunks, root_box, skewed_tree, uniform_tree


def _unit(v):
    return (v / np.linalg.norm(v, axis=1, keepdims=True)).astype(np.float32)


def _batch(o, d):
    n = len(o)
    return RayBatch(np.asarray(o, np.float32), _unit(np.asarray(d, np.float64)), np.ones((n, 3), np.float32),
                    np.arange(n, dtype=np.int32), np.zeros(n, np.int32), np.zeros(n, np.uint64))


def first_hits_chunked(views: list[ChunkView], tree: ChunkTree, batch: RayBatch):
    """(global triangle id, t, chunks visited) of each ray; -1 for a miss."""
    n = len(batch)
    tri, t, visits = np.full(n, -1), np.full(n, np.inf), np.zeros(n, np.int64)
    chunk, tmin = enter(tree, batch.origin, batch.direction)
    batch.tmin = tmin
    ids = np.arange(n)
    while len(ids):
        live = chunk >= 0
        ids, chunk, batch = ids[live], chunk[live], batch.take(live)
        nxt_chunk = np.full(len(ids), -1)
        for k in np.unique(chunk):
            sel = np.flatnonzero(chunk == k)
            view = views[k]
            sub = batch.take(sel)
            prim, tk, _u, _v, nxt, t_exit = view.intersect(sub)
            visits[ids[sel]] += 1
            hit = prim >= 0
            tri[ids[sel[hit]]] = view.geometry.global_id[prim[hit]]
            t[ids[sel[hit]]] = tk[hit]
            nxt_chunk[sel[~hit]] = nxt[~hit]
            batch.tmin[sel[~hit]] = t_exit[~hit]
        chunk = nxt_chunk
    return tri, t, visits


def _views(scene, tree):
    header = scene.header()
    return [ChunkView(k, g, header, tree) for k, g in enumerate(bbox_chunks(scene, tree))]


def _compare(scene, accel, views, tree, batch, label):
    prim, t_ref, _u, _v = accel.intersect(batch.origin, batch.direction)
    tri, t, visits = first_hits_chunked(views, tree, batch.take(np.arange(len(batch))))
    assert np.array_equal(prim < 0, tri < 0), f"{label}: hit/miss differ on {(np.sum((prim < 0) != (tri < 0)))} rays"
    hit = prim >= 0
    same = tri[hit] == prim[hit]
    rel = np.abs(t[hit] - t_ref[hit]) / np.maximum(t_ref[hit], 1e-3 * scene.diagonal())
    assert np.all(rel < 1e-5), f"{label}: t differs by {rel.max():.2e}"
    # A different triangle is allowed only as a tie, where either answer is
    # right: the same hit distance (asserted above) on two triangles that
    # share a vertex (the ray passes through their common edge or corner)
    # or overlap in one plane (the Cornell box's ceiling holds the light's
    # footprint twice, facing up and down).
    a, b = prim[hit][~same], tri[hit][~same]
    corners_a = scene.vertices[scene.triangles[a]].astype(np.float64)     # (k, 3, 3)
    corners_b = scene.vertices[scene.triangles[b]].astype(np.float64)
    shared = (np.abs(corners_a[:, :, None, :] - corners_b[:, None, :, :]).max(-1) == 0).any((1, 2))
    normal = np.cross(corners_a[:, 1] - corners_a[:, 0], corners_a[:, 2] - corners_a[:, 0])
    normal /= np.linalg.norm(normal, axis=1, keepdims=True)
    off_plane = np.abs(np.einsum("kj,kij->ki", normal, corners_b - corners_a[:, :1])).max(1)
    coplanar = off_plane < 1e-6 * scene.diagonal()
    assert (shared | coplanar).all(), \
        f"{label}: {np.sum(~(shared | coplanar))} hits on a different triangle that is no tie"
    assert len(a) <= 1e-4 * hit.sum(), f"{label}: {len(a)} edge ties"
    return visits


@pytest.fixture(scope="module")
def glass_scene():
    scene = builtin.make("cornell-glass")
    accel = Accelerator(scene.vertices, scene.triangles, threads=2)
    return scene, accel


@pytest.mark.parametrize("cells", [(2, 2, 2), (3, 3, 3)])
def test_million_random_rays_match_unchunked(glass_scene, cells):
    scene, accel = glass_scene
    box = root_box(scene)
    tree = uniform_tree(box, cells)
    views = _views(scene, tree)
    rng = np.random.default_rng(sum(cells))
    n = 1_000_000
    origin = box[0] + rng.random((n, 3)) * (box[1] - box[0])
    batch = _batch(origin, rng.normal(size=(n, 3)))
    visits = _compare(scene, accel, views, tree, batch, f"{cells} random")
    assert visits.max() > 2  # rays really crossed portals


def test_rays_at_portal_edges_and_corners(glass_scene):
    scene, accel = glass_scene
    box = root_box(scene)
    tree = uniform_tree(box, (3, 3, 3))
    views = _views(scene, tree)
    rng = np.random.default_rng(7)
    # Targets on the lattice: corners (where 8 chunks meet) and points on
    # edges (4 chunks), approached from random origins.
    lattice = [np.linspace(box[0, a], box[1, a], 4)[1:-1] for a in range(3)]
    corners = np.stack(np.meshgrid(*lattice, indexing="ij"), -1).reshape(-1, 3)
    n = 200_000
    target = corners[rng.integers(len(corners), size=n)]
    on_edge = rng.random(n) < 0.5
    axis = rng.integers(3, size=n)
    slide = rng.uniform(box[0], box[1], size=(n, 3))
    rows = np.flatnonzero(on_edge)
    target[rows, axis[rows]] = slide[rows, axis[rows]]
    origin = box[0] + rng.random((n, 3)) * (box[1] - box[0])
    batch = _batch(origin, target - origin)
    _compare(scene, accel, views, tree, batch, "edges and corners")


def test_rays_in_and_on_portal_planes(glass_scene):
    scene, accel = glass_scene
    box = root_box(scene)
    tree = uniform_tree(box, (3, 3, 3))
    views = _views(scene, tree)
    rng = np.random.default_rng(11)
    n = 100_000
    origin = box[0] + rng.random((n, 3)) * (box[1] - box[0])
    direction = rng.normal(size=(n, 3))
    # Put each origin exactly on one portal plane (float32-exact values).
    inner = tree.split[tree.axis >= 0].astype(np.float32)
    axes = tree.axis[tree.axis >= 0]
    pick = rng.integers(len(inner), size=n)
    origin[np.arange(n), axes[pick]] = inner[pick]
    # Half of them also travel inside that plane.
    lying = rng.random(n) < 0.5
    direction[np.flatnonzero(lying), axes[pick][lying]] = 0.0
    batch = _batch(origin, direction)
    batch.origin[np.arange(n), axes[pick]] = inner[pick]
    _compare(scene, accel, views, tree, batch, "portal planes")


def test_t_junctions_and_skewed_trees(glass_scene):
    scene, accel = glass_scene
    box = root_box(scene)
    tree = skewed_tree(box, np.random.default_rng(5), 9)
    views = _views(scene, tree)
    rng = np.random.default_rng(6)
    n = 200_000
    origin = box[0] + rng.random((n, 3)) * (box[1] - box[0])
    _compare(scene, accel, views, tree, _batch(origin, rng.normal(size=(n, 3))), "skewed")


def test_camera_outside_and_rays_leaving_the_scene(glass_scene):
    scene, accel = glass_scene
    box = root_box(scene)
    tree = uniform_tree(box, (2, 2, 2))
    views = _views(scene, tree)
    rng = np.random.default_rng(3)
    n = 50_000
    # From far outside, aimed at random points of the box, and away from it.
    origin = np.array([278.0, 273.0, -800.0]) + rng.normal(scale=50, size=(n, 3))
    target = box[0] + rng.random((n, 3)) * (box[1] - box[0])
    direction = target - origin
    direction[: n // 10] *= -1
    _compare(scene, accel, views, tree, _batch(origin, direction), "outside")
    chunk, _ = enter(tree, origin[: n // 10].astype(np.float32), _unit(direction[: n // 10]))
    assert np.all(chunk == -1)


def test_exit_through_a_corner_goes_to_the_diagonal_neighbour():
    box = np.array([[0.0, 0, 0], [2, 2, 2]])
    tree = uniform_tree(box, (2, 2, 2))
    start = tree.locate(np.array([[0.5, 0.5, 0.5]]), np.array([[1.0, 1, 1]]))[0]
    o = np.array([[0.5, 0.5, 0.5]], np.float32)
    d = _unit(np.array([[1.0, 1, 1]]))
    t_exit, nxt = exit_chunk(tree, start, o, d)
    diagonal = tree.locate(np.array([[1.5, 1.5, 1.5]]), np.array([[1.0, 1, 1]]))[0]
    assert nxt[0] == diagonal != start
    assert t_exit[0] == pytest.approx(np.sqrt(3) / 2, rel=1e-6)
    # Leaving the root box through its corner: escaped.
    t2, nxt2 = exit_chunk(tree, diagonal, o, d)
    assert nxt2[0] == -1 and t2[0] == pytest.approx(1.5 * np.sqrt(3), rel=1e-6)


def test_hit_on_a_triangle_lying_in_a_portal_is_found_once():
    """A triangle lying exactly in the portal plane x = 1 belongs to both
    chunks; rays crossing it hit it once, from either side."""
    from dosppm_core.scene.model import Camera, Material, SceneBuilder
    b = SceneBuilder(source="test")
    b.camera = Camera((1, 1, -5), (1, 1, 0), (0, 1, 0), 40, 8, 8)
    b.add_material(Material("white", "diffuse", reflectance=(0.5, 0.5, 0.5)))
    b.add_material(Material("light", "diffuse", emission=(1, 1, 1)))
    wall = np.array([[1.0, 0, 0], [1, 2, 0], [1, 2, 2], [1, 0, 2]])
    b.add_mesh(wall, np.array([[0, 1, 2], [0, 2, 3]]), "white", "wall")
    b.add_mesh(np.array([[0.0, 0, 0], [2, 0, 0], [2, 0, 2]]), np.array([[0, 1, 2]]), "light", "floor")
    scene = b.build()
    box = np.array([[0.0, -0.01, -0.01], [2, 2.01, 2.01]])
    tree = uniform_tree(box, (2, 1, 1))
    assert tree.split[0] == 1.0
    views = _views(scene, tree)
    assert all(0 in v.geometry.global_id for v in views)  # duplicated in both
    rng = np.random.default_rng(0)
    n = 20_000
    yz = rng.uniform(0.1, 1.9, size=(n, 2))
    sign = np.where(rng.random(n) < 0.5, -1.0, 1.0)
    origin = np.column_stack([1 - 0.7 * sign, yz])
    direction = np.column_stack([sign, rng.normal(scale=0.1, size=(n, 2))])
    batch = _batch(origin, direction)
    prim, _t, _u, _v = Accelerator(scene.vertices, scene.triangles).intersect(batch.origin, batch.direction)
    tri, t, visits = first_hits_chunked(views, tree, batch)
    on_wall = np.isin(prim, [0, 1])
    assert on_wall.mean() > 0.9
    assert np.array_equal(tri[on_wall], prim[on_wall])   # never lost
    assert np.all(visits[on_wall] <= 2)


@pytest.mark.parametrize("chunks", [8, 27])
def test_million_rays_through_a_real_store_match_unchunked(glass_scene, chunk_store, chunks):
    """The same check on the subdivider's own output: kd-tree splits at
    bin boundaries and exact triangle-box insertion."""
    scene, accel = glass_scene
    store = chunk_store(scene, chunks=chunks)
    views = [ChunkView(k, store.load(k), store.header, store.tree) for k in range(store.chunk_count)]
    box = store.tree.root_box
    rng = np.random.default_rng(chunks)
    n = 1_000_000
    origin = box[0] + rng.random((n, 3)) * (box[1] - box[0])
    visits = _compare(scene, accel, views, store.tree, _batch(origin, rng.normal(size=(n, 3))),
                      f"store c={chunks}")
    assert visits.max() > 2
