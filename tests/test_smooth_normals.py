"""Smooth shading normals (`kernels.smooth`, `scene.normals`): Mitsuba's
interpolated vertex normals on meshes and its analytic sphere's normal."""
import math
import os

import numpy as np
import pytest

from dosppm_core.accel import Accelerator
from dosppm_core.kernels import paths
from dosppm_core.scene.mitsuba import load_mitsuba_xml
from dosppm_core.scene.model import Camera, Material, SceneBuilder
from dosppm_core.scene.normals import angle_weighted_normals
from dosppm_core.trace import EPS_REL, NO_CULL, SurfaceData
from tests.helpers.paths import SHARED
from tests.helpers.renders import leaves

MESHES = os.path.join(SHARED, "scenes/mitsuba-data/common/meshes")

SPHERE = """<scene version="3.0.0">
  <sensor type="perspective"><float name="fov" value="40"/>
    <transform name="to_world"><lookat origin="0,-6,1" target="0,0,0" up="0,0,1"/></transform>
    <film type="hdrfilm"><integer name="width" value="24"/><integer name="height" value="24"/>
      <rfilter type="box"/></film>
  </sensor>
  <shape type="sphere"><point name="center" x="0.3" y="0.2" z="0.1"/><float name="radius" value="0.8"/>
    <bsdf type="{bsdf}"/></shape>
  <shape type="rectangle"><transform name="to_world"><scale value="3"/><translate z="-1"/></transform>
    <bsdf type="diffuse"><rgb name="reflectance" value="0.6"/></bsdf></shape>
  <shape type="rectangle"><transform name="to_world"><scale value="0.5"/><rotate x="1" angle="180"/>
    <translate x="1" z="3"/></transform>
    <emitter type="area"><rgb name="radiance" value="20"/></emitter></shape>
</scene>
"""


def _sphere_scene(tmp_path, bsdf="conductor"):
    path = tmp_path / "sphere.xml"
    path.write_text(SPHERE.format(bsdf=bsdf))
    return load_mitsuba_xml(str(path))


def _rays_at_sphere(n, seed=3):
    """Rays from a ring around the sphere (centre (0.3, 0.2, 0.1), radius
    0.8) aimed at points spread over its visible side."""
    rng = np.random.default_rng(seed)
    centre = np.array([0.3, 0.2, 0.1])
    origin = np.tile(centre + [0.0, -5.0, 0.5], (n, 1))
    target = centre + rng.uniform(-0.5, 0.5, (n, 3)) * [1, 0, 1]
    d = target - origin
    return origin.astype(np.float32), (d / np.linalg.norm(d, axis=1, keepdims=True)).astype(np.float32)


def test_a_smooth_mirror_sphere_reflects_about_the_exact_sphere_normal(tmp_path):
    """Mitsuba's sphere is analytic: an eye path off our (tessellated)
    mirror sphere leaves as reflected about (p - centre) / |p - centre|,
    to float precision; flat facets were off by up to their chord angle."""
    scene = _sphere_scene(tmp_path)
    assert len(scene.normals) == len(scene.vertices)
    surf = SurfaceData.from_scene(scene)
    origin, direction = _rays_at_sphere(200)
    accel = Accelerator(scene.vertices, scene.triangles)
    try:
        prim, _t, u, v = accel.intersect(origin, direction)
    finally:
        accel.close()
    assert np.all(prim >= 0)
    n = len(prim)
    rays = (direction, np.ones((n, 3), np.float32), np.zeros(n, np.int32), np.arange(n, dtype=np.uint64) + 1)
    _ends, _lit, _hp, (g, no, nd, _nw, _st) = paths.advance_eye_paths_serial(
        rays, (prim, u, v), surf, surf.normals, surf.material_extras, 8, EPS_REL)
    assert len(g) == n
    corners = scene.vertices[scene.triangles[prim[g]]].astype(np.float64)
    b = np.stack([1 - u[g] - v[g], u[g], v[g]], 1).astype(np.float64)
    p = np.einsum("ij,ijk->ik", b, corners)
    s = p - [0.3, 0.2, 0.1]
    s /= np.linalg.norm(s, axis=1, keepdims=True)
    w = -direction[g].astype(np.float64)
    expected = 2 * np.einsum("ij,ij->i", w, s)[:, None] * s - w
    assert np.abs(expected - nd).max() < 1e-5      # facets: up to their chord angle, about 1e-2


def _tilted_triangle_scene(normals):
    """One diffuse triangle in z = 0 (front +z) with the given vertex
    normals, a point light above and a camera."""
    b = SceneBuilder()
    b.add_material(Material("white", reflectance=(0.5, 0.5, 0.5)))
    b.add_mesh([(-1, -1, 0), (1, -1, 0), (0, 1, 0)], [(0, 1, 2)], "white", "tri", normals=normals)
    b.add_point_light((0, 0, 1), (1, 1, 1), "light")
    b.camera = Camera(position=(0, -2, 1), look_at=(0, 0, 0), up=(0, 0, 1), fov_deg=40, width=4, height=4)
    return b.build()


def test_a_photon_deposits_its_flux_times_ws_over_wn():
    """Veach's adjoint: a photon from w deposits flux |w.s| / |w.n| on a
    smooth surface (s its interpolated normal, n the face's); a flat one
    deposits its flux."""
    tilt = np.array([0.3, 0.0, 1.0]) / np.linalg.norm([0.3, 0.0, 1.0])
    w = np.array([-0.5, 0.2, 0.8]) / np.linalg.norm([-0.5, 0.2, 0.8])
    got = {}
    for smooth in (False, True):
        scene = _tilted_triangle_scene(np.tile(tilt, (3, 1)) if smooth else None)
        surf = SurfaceData.from_scene(scene)
        one = np.ones(1)
        rays = ((-w[None]).astype(np.float32), np.ones((1, 3), np.float32), np.zeros(1, np.int32),
                np.ones(1, np.uint64), np.zeros(1, np.int64), np.zeros(1, np.int32))
        hits = (np.zeros(1, np.int32), np.float32(0.3) * one.astype(np.float32), np.float32(0.3) * one.astype(np.float32))
        _ends, _culled, dep, _nxt = paths.scatter_photons(rays, hits, surf, surf.smooth_normals, surf.material_extras,
                                                          NO_CULL, 8, 0, EPS_REL)
        got[smooth] = dep[2][0].astype(np.float64)
    assert got[False] == pytest.approx([1, 1, 1], abs=1e-6)
    assert got[True] == pytest.approx(np.full(3, (w @ tilt) / w[2]), rel=1e-5)


def test_vertex_normals_move_with_the_inverse_transpose_and_face_normals_turns_them_off(tmp_path):
    """An OBJ's vn under a non-uniform to_world become M^-T vn, normalised;
    face_normals="true" stores none; a mesh without vn gets Mitsuba's
    computed ones."""
    obj = tmp_path / "quad.obj"
    obj.write_text("v -1 -1 0\nv 1 -1 0\nv 1 1 0\nv -1 1 0\n"
                   "vn 0.2 0 1\nvn -0.2 0 1\nvn 0 0.3 1\nvn 0 0 1\n"
                   "f 1//1 2//2 3//3\nf 1//1 3//3 4//4\n")
    bare = tmp_path / "bare.obj"
    bare.write_text("v -1 -1 0\nv 1 -1 0\nv 1 1 0\nv -1 1 0\nf 1 2 3\nf 1 3 4\n")
    scale = np.array([2.0, 1.0, 0.5])

    def load(filename, extra=""):
        text = SPHERE.format(bsdf="diffuse").replace(
            '<shape type="sphere">',
            f'<shape type="obj"><string name="filename" value="{filename}"/>{extra}'
            f'<transform name="to_world"><scale x="2" y="1" z="0.5"/></transform>'
            '<bsdf type="diffuse"/></shape>\n  <shape type="sphere">')
        (tmp_path / "s.xml").write_text(text)
        return load_mitsuba_xml(str(tmp_path / "s.xml"))

    scene = load(obj)
    first = np.arange(4)        # the OBJ comes first, its vertices unshared with anything
    assert np.allclose(scene.vertices[first], [[-2, -1, 0], [2, -1, 0], [2, 1, 0], [-2, 1, 0]])
    vn = np.array([[0.2, 0, 1], [-0.2, 0, 1], [0, 0.3, 1], [0, 0, 1]]) / scale
    vn /= np.linalg.norm(vn, axis=1, keepdims=True)
    assert np.allclose(scene.normals[first], vn, atol=1e-6)
    flat = load(obj, '<boolean name="face_normals" value="true"/>')
    assert not np.any(flat.normals[first])          # the sphere still has its own
    computed = load(bare)
    assert np.allclose(computed.normals[first], [0, 0, 1], atol=1e-6)


@pytest.mark.reference
def test_computed_normals_are_mitsubas(mi):
    """Without normals in the file, Mitsuba computes angle-weighted ones
    (Thuermer and Wuethrich): ours on the teapot equal them."""
    shape = mi.load_dict({"type": "ply", "filename": f"{MESHES}/teapot.ply"})
    params = mi.traverse(shape)
    v = np.array(params["vertex_positions"]).reshape(-1, 3)
    f = np.array(params["faces"]).reshape(-1, 3).astype(np.int64)
    theirs = np.array(params["vertex_normals"]).reshape(-1, 3)
    ours = angle_weighted_normals(v, f)
    assert np.abs(ours - theirs).max() < 1e-4


def test_a_flat_mesh_with_its_face_normals_as_vertex_normals_renders_as_flat():
    """Vertex normals equal to the face normal take the smooth path (every
    kernel) and render the flat image up to float noise."""
    from dosppm_core.modes.sppm import Renderer
    from dosppm_core.scene.builtin import cornell_box
    from dosppm_core.settings import RenderSettings
    base = cornell_box()
    corners = base.vertices[base.triangles]
    n = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    flat = type(base)(corners.reshape(-1, 3), np.arange(corners.size // 3, dtype=np.int32).reshape(-1, 3),
                      base.tri_material, base.materials, base.lights, base.camera)
    smooth = type(base)(flat.vertices, flat.triangles, flat.tri_material, flat.materials, flat.lights,
                        flat.camera, normals=np.repeat(n, 3, axis=0).astype(np.float32))
    images = []
    for scene in (flat, smooth):
        r = Renderer(scene, RenderSettings(seed=5, photons_per_iteration=20_000))
        try:
            for _ in range(2):
                r.run_iteration()
            images.append(np.asarray(r.image()))
        finally:
            r.close()
    ref, img = images
    assert ref.mean() > 0
    assert np.abs(img - ref).mean() < 1e-3 * ref.mean()


def test_smooth_scene_chunked_equals_unchunked(tmp_path, chunk_store):
    """A mirror sphere (smooth) over a floor, cut into 2 chunks by the real
    subdivider and rendered by OSPPM from the store (each iteration
    drained): the unchunked image bit for bit, as portals promise; the
    chunks carry the vertex normals. (So do Mitsuba's arealight and
    roughdielectric sphere grids in 2, 4 and 8 chunks, measured.)"""
    from dosppm_core.modes.osppm import OutOfCoreRenderer
    from dosppm_core.modes.sppm import Renderer
    from dosppm_core.settings import RenderSettings
    scene = _sphere_scene(tmp_path)
    settings = RenderSettings(seed=11, photons_per_iteration=30_000)
    store = chunk_store(scene, chunks=2)
    assert store.chunk_count == 2
    assert any(len(store.load(k).normals) for k in range(2))
    images = []
    for r in (Renderer(scene, settings), OutOfCoreRenderer(store, settings, pipelined=False)):
        try:
            for _ in range(3):
                r.run_iteration()
            images.append(np.asarray(r.image()))
        finally:
            r.close()
    ref, img = images
    assert ref.mean() > 0
    assert img.tobytes() == ref.tobytes()


def test_the_service_renders_a_smooth_scene_as_one_process(tmp_path, chunk_store):
    """The smooth mirror sphere cut into 2 chunks by the real subdivider,
    rendered by the service in one process (a server and 2 tracers over
    the wire protocol, `services.inproc`): each eye iteration makes
    exactly single-process SPPM's hit points (the same eye rays, reflected
    about the same normals in the tracers' chunks), and the image is SPPM's
    at the same seed within SPPM's own noise across seeds (the service
    applies photons in other batches: not bit for bit). This is where a
    normal lost on the way to a tracer (its chunk view, a portal) shows."""
    from dosppm_core.modes.sppm import Renderer
    from dosppm_core.settings import RenderSettings
    from services.inproc import InProcessCluster
    from tests.helpers.cluster import assert_same_within_noise
    scene = _sphere_scene(tmp_path)
    iterations, photons = 6, 60_000

    def settings(seed):
        return RenderSettings(seed=seed, photons_per_iteration=photons, photons_per_job=1024, tile_pixels=144,
                              threads=1)
    sppm, hit_points = {}, []
    for seed in (5, 9):
        r = Renderer(scene, settings(seed))
        try:
            for _ in range(iterations):
                before = r.sppm.hit_point_total
                r.run_iteration()
                hit_points.append(r.sppm.hit_point_total - before)
            sppm[seed] = np.asarray(r.image())
        finally:
            r.close()
    store = chunk_store(scene, chunks=2)
    assert all(len(store.load(k).normals) for k in range(2))      # the sphere is cut
    c = InProcessCluster(store, settings(5), tracers=2)
    per_iteration, seen = [], 0
    try:
        while c.server.counters["photons_emitted"] < iterations * photons:
            c.round()
            if c.server.eye_completed > len(per_iteration):
                per_iteration.append(c.server.counters["hit_points"] - seen)
                seen = c.server.counters["hit_points"]
        c.drain()
    finally:
        c.close()
    portal_rays = sum(t.counters["portal_rays_out"] for t in c.tracers.values())
    assert portal_rays > 0 and len(per_iteration) >= 3
    # As many eye iterations as SPPM's: the light seen in the mirror (a few
    # pixels' worth of the mean) is averaged over as many eye samples.
    assert c.server.eye_completed == iterations
    assert per_iteration[:3] == hit_points[:3]
    assert_same_within_noise(np.asarray(c.image()), sppm[5], sppm[9])



def test_a_flat_plain_scene_runs_the_pruned_eye_bounce_with_the_general_ones_result():
    """A scene of flat meshes and plain materials gets the eye bounce
    compiled without the smooth-normal and material branches (`normals`
    and `extras` None); the general kernel, fed the empty normals and the
    bsdf rows, gives the same arrays bit for bit, bounce after bounce."""
    from dosppm_core.jobs import RayBatch
    from dosppm_core.trace import eye_ray_job
    from tests.helpers.scenes import small_scene

    scene = small_scene("cornell-glass", 32)
    surf = SurfaceData.from_scene(scene)
    assert surf.smooth_normals is None and surf.material_extras is None
    accel = Accelerator(scene.vertices, scene.triangles)
    batch, bounces = eye_ray_job(scene, 3, 0, 0, 32 * 32), 0
    try:
        while len(batch) and bounces < 6:
            prim, _t, u, v = accel.intersect(batch.origin, batch.direction)
            rays = (batch.direction, batch.weight, batch.depth, batch.rng)
            pruned = paths.advance_eye_paths_serial(rays, (prim, u, v), surf, None, None, 10, EPS_REL)
            general = paths.advance_eye_paths_serial(rays, (prim, u, v), surf, surf.normals, surf.bsdf, 10,
                                                     EPS_REL)
            for x, y in zip(leaves(pruned), leaves(general), strict=True):
                np.testing.assert_array_equal(x, y)
            g, no, nd, nw, st = pruned[3]
            batch = RayBatch(no, nd, nw, batch.pixel[g], batch.depth[g] + 1, st)
            bounces += 1
    finally:
        accel.close()
    assert bounces >= 3


def test_a_flat_plain_scene_runs_the_pruned_photon_bounce_with_the_general_ones_result():
    """As for the eye bounce: the photon bounce compiled for `normals` and
    `extras` None gives the general kernel's deposits and continuing paths
    bit for bit, bounce after bounce (glass included: cornell-glass)."""
    from dosppm_core.jobs import RayBatch
    from dosppm_core.trace import emit_photon_job
    from tests.helpers.scenes import small_scene

    scene = small_scene("cornell-glass", 16)
    surf = SurfaceData.from_scene(scene)
    assert surf.smooth_normals is None and surf.material_extras is None
    accel = Accelerator(scene.vertices, scene.triangles)
    batch, bounces, deposits = emit_photon_job(scene, 7, 0, 20_000, surf.eps_abs), 0, 0
    try:
        while len(batch) and bounces < 6:
            prim, _t, u, v = accel.intersect(batch.origin, batch.direction)
            rays = (batch.direction, batch.weight, batch.depth, batch.rng, batch.job, batch.pixel)
            args = ((prim, u, v), surf)
            tail = (NO_CULL, 10, 0, EPS_REL)
            pruned = paths.scatter_photons(rays, *args, None, None, *tail)
            general = paths.scatter_photons(rays, *args, surf.normals, surf.bsdf, *tail)
            for x, y in zip(leaves(pruned), leaves(general), strict=True):
                np.testing.assert_array_equal(x, y)
            deposits += len(pruned[2][0])
            no, nd, nf, st, depth, job, pixel = pruned[3]
            batch = RayBatch(no, nd, nf, pixel, depth, st, job=job)
            bounces += 1
    finally:
        accel.close()
    assert bounces >= 3 and deposits > 1000


def test_material_extras_are_there_for_a_mask_a_plastic_or_a_texture():
    from dosppm_core.scene.model import PLASTIC
    from tests.helpers.scenes import small_scene

    for change in (None, "opacity", "kind", "texture"):
        scene = small_scene("cornell-box", 8)
        m = scene.materials
        if change == "opacity":
            m.opacity[0] = 0.5
        elif change == "kind":
            m.kind[0] = PLASTIC
        elif change == "texture":
            m.texture[0] = 0
        extras = SurfaceData.from_scene(scene).material_extras
        assert (extras is None) == (change is None), change


def test_the_sponza_case_reads_a_flat_copy_as_its_pbrt_reference_was_made(tmp_path):
    """pbrt-v4 shades a PLY without normals flat, Mitsuba's reading (ours)
    smooth: the evaluation's sponza-point case reads a copy of the XML with
    face_normals set, the same triangles and no vertex normals, and
    `dosppm render` gets that copy (Scene.source)."""
    from harness import evaluate
    from harness.suites import SUITES

    suite = SUITES["sponza"]
    case = suite.cases[0]
    assert case.files.face_normals
    smooth = load_mitsuba_xml(os.path.join(SHARED, case.files.scene))
    flat = evaluate.suite_scene(suite, case, SHARED, str(tmp_path))
    assert flat.source.startswith(str(tmp_path)) and os.path.isfile(flat.source)
    assert len(smooth.normals) and np.abs(smooth.normals).sum(axis=1).min() > 0
    assert not np.any(flat.normals)
    np.testing.assert_array_equal(flat.vertices, smooth.vertices)
    np.testing.assert_array_equal(flat.triangles, smooth.triangles)
