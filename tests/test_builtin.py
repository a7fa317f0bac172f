"""Built-in scenes: the measured Cornell box equals Mitsuba's, the others
hold what they promise, and all are cheap and deterministic."""
import math
import os
import time
import xml.etree.ElementTree as ET

import numpy as np
import pytest
import trimesh

import dosppm_core.scene as scene_package
from dosppm_core.scene import builtin, loaders, model
from dosppm_core.scene.model import LIGHT_POINT, LIGHT_TRIANGLE, SceneError
from tests.helpers.paths import SHARED_SCENES, needs_shared_scenes

CBOX = os.path.join(SHARED_SCENES, "cornell_box", "mitsuba")
PARTS = ("floor", "ceiling", "back", "greenwall", "redwall", "smallbox", "largebox", "luminaire")


def _triangle_keys(vertices, faces):
    """Each triangle as its corners rounded to 1e-3 mm, rotated to start at
    the smallest corner: equal keys mean equal triangles with equal winding."""
    keys = []
    for tri in np.round(np.asarray(vertices, np.float64)[faces], 3):
        corners = [tuple(c) for c in tri]
        k = corners.index(min(corners))
        keys.append(tuple(corners[k:] + corners[:k]))
    return sorted(keys)


def _material_of(scene, name):
    return scene.tri_material == scene.materials.names.index(name)


def _part(scene, name):
    sel = _material_of(scene, name)
    return scene.vertices.astype(np.float64), scene.triangles[sel]


def _normals(vertices, faces):
    v = vertices[faces]
    return np.cross(v[:, 1] - v[:, 0], v[:, 2] - v[:, 0])


@pytest.mark.parametrize("name", list(builtin.SCENES))
def test_every_scene_builds_fast_and_deterministically(name):
    start = time.perf_counter()
    a = builtin.make(name)
    assert time.perf_counter() - start < 1.0
    b = builtin.make(name)
    assert np.array_equal(a.vertices, b.vertices) and np.array_equal(a.triangles, b.triangles)
    assert a.name == name and a.lights.total_power > 0


def test_registry():
    assert builtin.DEFAULT in builtin.SCENES
    assert set(builtin.SCENES) == {"cornell-box", "cornell-caustic", "cornell-glass", "furnace-sphere",
                                   "thin-wall", "far-from-origin", "many-lights", "glossy-floor",
                                   "glass-small-light", "cardioid"}
    with pytest.raises(SceneError, match="cornell-box.*furnace-sphere"):
        builtin.make("cornell-dragon")


def test_package_exports_the_model_and_the_loaders():
    """`from dosppm_core.scene import Scene, load_scene` works, and the
    names are the model's and the loaders' own."""
    assert scene_package.Scene is model.Scene and scene_package.SceneError is model.SceneError
    assert scene_package.load_scene is loaders.load_scene
    assert all(hasattr(scene_package, name) for name in scene_package.__all__)
    assert isinstance(scene_package.load_scene("cornell-box"), scene_package.Scene)


def test_loader_dispatches_built_in_names():
    scene = loaders.load_scene("cornell-box", width=64, height=48)
    assert scene.triangle_count == 38
    assert (scene.camera.width, scene.camera.height) == (64, 48)


@needs_shared_scenes
def test_cornell_box_triangles_equal_mitsubas_meshes():
    expected = []
    for part in PARTS:
        mesh = trimesh.load(os.path.join(CBOX, "meshes", f"cbox_{part}.obj"), force="mesh", process=False)
        vertices = np.asarray(mesh.vertices, np.float64)
        if part == "luminaire":  # cbox.xml translates it by y -0.5
            vertices = vertices + [0.0, -0.5, 0.0]
        expected += _triangle_keys(vertices, mesh.faces)
    scene = builtin.make("cornell-box")
    assert _triangle_keys(scene.vertices, scene.triangles) == sorted(expected)


@needs_shared_scenes
def test_cornell_materials_equal_mitsubas_rgb_fragment():
    root = ET.parse(os.path.join(CBOX, "fragments", "bsdfs-rgb.xml")).getroot()
    scene = builtin.make("cornell-box")
    for bsdf in root.iter("bsdf"):
        rgb = [float(x) for x in bsdf.find("rgb").get("value").split(",")]
        mid = scene.materials.names.index(bsdf.get("id"))
        assert np.allclose(scene.materials.reflectance[mid], rgb, rtol=1e-6)
        assert not scene.materials.two_sided[mid]  # Mitsuba's diffuse is one-sided
    emitter = ET.parse(os.path.join(CBOX, "cbox-rgb.xml")).getroot().find("emitter/rgb")
    radiance = [float(x) for x in emitter.get("value").split(",")]
    assert np.allclose(scene.materials.emission[scene.materials.names.index("light")], radiance)


def test_cornell_camera_is_mitsubas():
    cam = builtin.make("cornell-box").camera
    assert tuple(cam.position) == (278, 273, -800) and tuple(cam.look_at) == (278, 273, -799)
    assert tuple(cam.up) == (0, 1, 0)
    assert (cam.fov_deg, cam.fov_axis, cam.width, cam.height) == (39.3077, "smaller", 256, 256)


def test_cornell_luminaire_emits_down_and_walls_face_in():
    scene = builtin.make("cornell-box")
    lights = scene.lights.kind == LIGHT_TRIANGLE
    n = np.cross(scene.lights.p1[lights] - scene.lights.p0[lights], scene.lights.p2[lights] - scene.lights.p0[lights])
    assert lights.sum() == 2 and np.all(n[:, 1] < 0) and np.allclose(n[:, [0, 2]], 0)
    assert np.allclose(scene.lights.p0[lights][:, 1], 548.3)
    centre = np.array([278.0, 274.4, 279.6])
    for mat in ("red", "green"):
        v, f = _part(scene, mat)
        n = _normals(v, f)
        assert np.all(np.sum(n * (centre - v[f].mean(1)), axis=1) > 0)
    # White: floor, back and ceiling face in, except the ceiling's hidden
    # reversed quad at the light's footprint (2 triangles facing up).
    v, f = _part(scene, "white")
    inward = np.sum(_normals(v, f) * (centre - v[f].mean(1)), axis=1) > 0
    assert inward.sum() == len(f) - 2
    hidden = v[f[~inward]].reshape(-1, 3)
    assert np.all(hidden[:, 1] == np.float32(548.8))
    assert hidden[:, 0].min() == 213 and hidden[:, 0].max() == 343


def _closed_part(scene, name):
    v, f = _part(scene, name)
    used = np.unique(f)
    return trimesh.Trimesh(v[used], np.searchsorted(used, f), process=False)


def test_cornell_blocks_are_closed_and_face_out():
    mesh = _closed_part(builtin.make("cornell-box"), "box")
    assert len(mesh.faces) == 24
    # The small block's 12 triangles come first, then the large block's
    # (no mesh.split: it needs a graph engine that the test extras lack).
    for faces in (mesh.faces[:12], mesh.faces[12:]):
        block = trimesh.Trimesh(mesh.vertices, faces)
        block.merge_vertices()  # Mitsuba's blocks list each quad's corners apart
        assert block.is_watertight and block.volume > 0


def test_cornell_caustic_has_a_glass_and_a_mirror_sphere_inside_the_box():
    scene = builtin.make("cornell-caustic")
    assert "box" not in scene.materials.names  # the blocks are gone
    m = scene.materials
    glass, mirror = m.names.index("glass"), m.names.index("mirror")
    assert m.kind[glass] == 2 and m.ior[glass] == pytest.approx(1.5) and m.kind[mirror] == 1
    centres = []
    for name in ("glass", "mirror"):
        mesh = _closed_part(scene, name)
        assert mesh.is_watertight and mesh.volume > 0 and len(mesh.faces) >= 5000
        lo, hi = mesh.bounds
        assert np.all(lo > [0, 0, 0]) and np.all(hi < [549.6, 548.8, 559.2])
        assert 0 < lo[1] < 2  # resting just above the floor
        centres.append((lo + hi) / 2)
        radius = (hi - lo).max() / 2
    assert np.linalg.norm(centres[0] - centres[1]) > 2 * radius  # apart
    assert centres[1][2] > centres[0][2]  # mirror at the back, glass in front


def test_cornell_glass_holds_a_watertight_high_poly_glass_object():
    scene = builtin.make("cornell-glass")
    mesh = _closed_part(scene, "glass")
    assert len(mesh.faces) >= 100_000
    assert mesh.is_watertight and mesh.is_winding_consistent and mesh.volume > 0
    lo, hi = mesh.bounds
    assert np.all(lo > [0, 0, 0]) and np.all(hi < [549.6, 548.3, 559.2])
    assert scene.materials.kind[scene.materials.names.index("glass")] == 2
    assert builtin.DEFAULT == "cornell-glass"


def test_furnace_sphere_layout():
    scene = builtin.furnace_sphere(albedo=0.3, intensity=2.0, subdivisions=3)
    assert scene.triangle_count == 20 * 4 ** 3
    assert np.allclose(np.linalg.norm(scene.vertices, axis=1), 1.0, atol=1e-6)
    assert np.allclose(scene.materials.reflectance, 0.3) and scene.materials.two_sided.all()
    assert list(scene.lights.kind) == [LIGHT_POINT]
    assert np.allclose(scene.lights.p0[0], 0) and np.allclose(scene.lights.value[0], 2.0)
    assert np.allclose(scene.lights.power, 4 * math.pi * 2.0)
    cam = scene.camera
    assert np.allclose(cam.position, 0) and (cam.width, cam.height, cam.fov_deg) == (32, 32, 60)
    mesh = trimesh.Trimesh(scene.vertices, scene.triangles, process=False)
    assert mesh.is_watertight
    doc = builtin.furnace_sphere.__doc__
    assert "rho * I / (pi * R^2 * (1 - rho))" in doc and "sum_{k < D} rho^k" in doc


def test_a_mesh_file_is_placed_in_the_cornell_box_in_glass(tmp_path):
    # `dosppm bench --mesh` and the equal-work benchmark's dragon scene.
    from dosppm_core.scene.builtin import cornell_with_mesh
    obj = tmp_path / "tet.obj"
    obj.write_text("v 0 0 0\nv 2 0 0\nv 0 2 0\nv 0 0 2\nf 1 3 2\nf 1 2 4\nf 1 4 3\nf 2 3 4\n")
    scene = cornell_with_mesh(str(obj), size_mm=100.0)
    assert scene.name == "cornell-tet"
    glass = scene.tri_material == scene.tri_material[-1]
    assert glass.sum() == 4                                  # the mesh's faces, in one material of their own
    v = scene.vertices[np.unique(scene.triangles[glass])].astype(np.float64)
    assert np.isclose(np.ptp(v, axis=0).max(), 100.0, atol=1e-3)   # scaled to size_mm
    floor = scene.vertices[:, 1].min()
    assert np.isclose(v[:, 1].min() - floor, 1.0, atol=1e-3)       # resting 1 mm above the floor
