"""The Embree aggregate against embreex's own wrapper of the same library:
the same closest hit for every ray, tmax honoured, close() safe while a
trace runs on another thread."""
import threading

import numpy as np
import pytest
import trimesh

from dosppm_core.accel import MISS, Accelerator
from dosppm_core.chunks.subdivide import EMBREE_BYTES_PER_TRIANGLE
from harness.embree_memory import measure_embree_bytes_per_triangle


def _sphere_rays(n, seed=1):
    rng = np.random.default_rng(seed)
    origin = (rng.normal(size=(n, 3)) * 0.7).astype(np.float32)   # inside and outside
    direction = rng.normal(size=(n, 3)).astype(np.float32)
    return origin, direction


@pytest.fixture(scope="module")
def sphere():
    mesh = trimesh.creation.icosphere(subdivisions=5)
    return np.asarray(mesh.vertices, np.float32), np.asarray(mesh.faces, np.int32)


@pytest.mark.parametrize("threads", [1, 2])
def test_closest_hit_equals_embreex(sphere, threads):
    # embreex's wrapper is the reference, imported here only: accel.py stays
    # the one module of the library that drives Embree.
    from embreex import rtcore_scene as rtcs
    from embreex.mesh_construction import TriangleMesh
    vertices, triangles = sphere
    origin, direction = _sphere_rays(200_000)
    reference = rtcs.EmbreeScene()
    TriangleMesh(reference, vertices, triangles)
    r = reference.run(origin, direction, output=1)
    prim, t, u, v = Accelerator(vertices, triangles, threads=threads).intersect(origin, direction)
    assert (prim >= 0).mean() > 0.5 and (prim == MISS).any()   # both cases occur
    np.testing.assert_array_equal(prim, r["primID"])
    hit = prim >= 0
    np.testing.assert_array_equal(t[hit], r["tfar"][hit])
    np.testing.assert_array_equal(u[hit], r["u"][hit])
    np.testing.assert_array_equal(v[hit], r["v"][hit])


def test_tmax_cuts_hits_and_is_not_modified(sphere):
    vertices, triangles = sphere
    origin, direction = _sphere_rays(50_000, seed=2)
    accel = Accelerator(vertices, triangles, threads=2)
    prim, t, _u, _v = accel.intersect(origin, direction)
    tmax = np.where(prim >= 0, t * 0.5, 1.0).astype(np.float32)
    kept = tmax.copy()
    prim2, t2, _u, _v = accel.intersect(origin, direction, tmax)
    np.testing.assert_array_equal(tmax, kept)
    # The sphere is convex from inside: halving t finds nothing before it.
    inside = np.linalg.norm(origin, axis=1) < 0.95
    assert inside.sum() > 1000
    assert (prim2[inside & (prim >= 0)] == MISS).all()
    np.testing.assert_array_equal(t2[prim2 == MISS], tmax[prim2 == MISS])


def test_close_waits_for_a_running_trace(sphere):
    vertices, triangles = sphere
    origin, direction = _sphere_rays(400_000, seed=3)
    accel = Accelerator(vertices, triangles, threads=1)
    out = {}
    worker = threading.Thread(target=lambda: out.setdefault("r", accel.intersect(origin, direction)))
    worker.start()
    while accel._users == 0 and worker.is_alive():   # the trace has begun
        pass
    accel.close()                      # must not free the BVH under the trace
    worker.join()
    assert (out["r"][0] >= 0).any()
    with pytest.raises(RuntimeError, match="after close"):
        accel.intersect(origin[:4], direction[:4])


def test_empty_batch_and_degenerate_triangle():
    accel = Accelerator(np.zeros((3, 3), np.float32), np.array([[0, 1, 2]], np.int32))
    prim, t, _u, _v = accel.intersect(np.zeros((0, 3), np.float32), np.zeros((0, 3), np.float32))
    assert prim.shape == (0,) and t.shape == (0,)
    prim, _t, _u, _v = accel.intersect(np.ones((5, 3), np.float32), -np.ones((5, 3), np.float32))
    assert (prim == MISS).all()


def test_memory_model_covers_a_bvh_build():
    """The subdivider's bytes per triangle must not underestimate what a
    BVH build really takes at its peak (worst case: random triangles)."""
    measured = measure_embree_bytes_per_triangle(1_000_000)
    assert 40 < measured <= EMBREE_BYTES_PER_TRIANGLE
