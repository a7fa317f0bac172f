"""The TOML scene format: the example loads, transforms land where they
should, meshes load from every common format, and every mistake is a
one-line SceneError naming the file and the key."""
import os

import numpy as np
import pytest
import trimesh

from dosppm_core.scene import loaders, shapes
from dosppm_core.scene.model import GLASS, LIGHT_POINT, LIGHT_SPOT, LIGHT_TRIANGLE, MATERIAL_KINDS, SceneError
from dosppm_core.scene.tomlfile import load_toml

EXAMPLE = os.path.join(os.path.dirname(__file__), "..", "examples", "cornell.toml")

BASE = """
[camera]
position = [0, 1, -5]
look_at = [0, 1, 0]
fov = 40
width = 32
height = 24

[materials.white]
type = "diffuse"
reflectance = 0.5

[materials.lamp]
type = "diffuse"
emission = [1, 2, 3]

[[shapes]]
type = "rectangle"
material = "lamp"
rotate = [1, 0, 0, 90]
translate = [0, 2, 0]
"""


def _write(tmp_path, text, name="scene.toml"):
    path = tmp_path / name
    path.write_text(text)
    return str(path)


def _load(tmp_path, text):
    return load_toml(_write(tmp_path, text))


def _normals(scene, mask=None):
    tris = scene.triangles if mask is None else scene.triangles[mask]
    v = scene.vertices.astype(np.float64)[tris]
    n = np.cross(v[:, 1] - v[:, 0], v[:, 2] - v[:, 0])
    return n / np.linalg.norm(n, axis=1, keepdims=True)


# -- the example and the happy path --------------------------------------------

def test_example_loads():
    scene = load_toml(EXAMPLE)
    assert scene.name == "cornell"
    assert scene.triangle_count == 6 * 2 + 12 + 2304
    assert np.allclose(scene.bounds(), [[0, 0, 0], [556, 548.8, 559.2]], atol=1e-3)
    assert scene.render_settings == {}
    lamp = scene.lights.kind == LIGHT_TRIANGLE
    assert lamp.sum() == 2 and np.allclose(scene.lights.value[lamp], [18.387, 10.9873, 2.75357])
    glass = scene.materials.names.index("glass")
    knot = trimesh.Trimesh(scene.vertices, scene.triangles[scene.tri_material == glass], process=False)
    knot.remove_unreferenced_vertices()
    assert knot.is_watertight and knot.volume > 0 and knot.bounds[0][1] > 0


def test_example_loads_through_the_dispatcher():
    assert loaders.load_scene(EXAMPLE, width=16, height=16).camera.width == 16


def test_example_walls_face_into_the_room_and_the_lamp_down():
    scene = load_toml(EXAMPLE)
    names = scene.materials.names
    expected = {"red": [-1, 0, 0], "green": [1, 0, 0], "light": [0, -1, 0]}
    for name, normal in expected.items():
        assert np.allclose(_normals(scene, scene.tri_material == names.index(name)), normal)


def test_camera_defaults_and_optional_lens(tmp_path):
    cam = _load(tmp_path, BASE).camera
    assert tuple(cam.up) == (0, 1, 0) and cam.fov_axis == "x" and cam.aperture_radius == 0
    assert cam.focus_distance == pytest.approx(5.0)  # focused on look_at
    lens = BASE.replace("height = 24", "height = 24\naperture_radius = 0.1\nfocus_distance = 7\nfov_axis = 'y'")
    cam = _load(tmp_path, lens).camera
    assert (cam.aperture_radius, cam.focus_distance, cam.fov_axis) == (0.1, 7.0, "y")


def test_materials_are_read(tmp_path):
    text = BASE + """
[materials.gold]
type = "glossy"
reflectance = [1.0, 0.8, 0.3]
roughness = 0.2
two_sided = false
[materials.water]
type = "glass"
ior = 1.33
[materials.chrome]
type = "mirror"
"""
    m = _load(tmp_path, text).materials
    gold, water, chrome = (m.names.index(n) for n in ("gold", "water", "chrome"))
    assert np.allclose(m.reflectance[gold], [1, 0.8, 0.3]) and m.roughness[gold] == pytest.approx(0.2)
    assert not m.two_sided[gold] and m.two_sided[m.names.index("white")]
    assert m.kind[water] == GLASS and m.ior[water] == pytest.approx(1.33)
    assert np.allclose(m.reflectance[chrome], 1.0)
    assert np.allclose(m.reflectance[m.names.index("white")], 0.5)


def test_lights_and_render_settings(tmp_path):
    text = BASE + """
[[lights]]
type = "point"
position = [0, 1, 0]
intensity = 5
[[lights]]
type = "spot"
position = [0, 2, 0]
target = [0, 0, 0]
intensity = [1, 2, 3]
cutoff_angle = 30
beam_width = 10
[render]
iterations = 10
alpha = 0.7
output = "out.exr"
progressive = true
"""
    scene = _load(tmp_path, text)
    kinds = list(scene.lights.kind)
    point, spot = kinds.index(LIGHT_POINT), kinds.index(LIGHT_SPOT)
    assert np.allclose(scene.lights.value[point], 5.0)
    assert np.allclose(scene.lights.p1[spot], [0, -1, 0])
    assert np.allclose(scene.lights.cone[spot, 2:], np.radians([30, 10]))
    assert scene.render_settings == {"iterations": 10, "alpha": 0.7, "output": "out.exr", "progressive": True}


def test_point_light_alone_is_enough(tmp_path):
    text = BASE.replace('material = "lamp"', 'material = "white"') + """
[[lights]]
type = "point"
position = [0, 1, 0]
intensity = 1
"""
    assert list(_load(tmp_path, text).lights.kind) == [LIGHT_POINT]


# -- transforms ----------------------------------------------------------------

def _shape_scene(tmp_path, shape_lines):
    """BASE plus one white shape; returns that shape's vertices (world)."""
    text = BASE + '\n[[shapes]]\nmaterial = "white"\n' + shape_lines
    scene = _load(tmp_path, text)
    mask = scene.tri_material == scene.materials.names.index("white")
    tris = scene.triangles[mask]
    return scene.vertices.astype(np.float64)[tris], _normals(scene, mask)


def _transformed(vertices, faces, m):
    return (vertices @ m[:3, :3].T + m[:3, 3])[faces]


def test_translate_rotate_scale_in_that_order(tmp_path):
    got, normals = _shape_scene(tmp_path, 'type = "rectangle"\nscale = [2, 3, 1]\n'
                                          'rotate = [0, 1, 0, 90]\ntranslate = [10, 20, 30]\n')
    v, f = shapes.rectangle()
    # Scale first, then +90 degrees about y (x -> -z, z -> x), then translate.
    expected = np.stack([v[:, 2] * 1 + 10, v[:, 1] * 3 + 20, -v[:, 0] * 2 + 30], axis=1)[f]
    assert np.allclose(got, expected, atol=1e-5)
    assert np.allclose(normals, [1, 0, 0])


def test_rotation_list_applies_in_listed_order(tmp_path):
    got, _ = _shape_scene(tmp_path, 'type = "box"\nrotate = [[0, 0, 1, 90], [1, 0, 0, 90]]\n')
    v, f = shapes.box()
    m = np.eye(4)
    m[:3, :3] = shapes.rotation_matrix((1, 0, 0), 90) @ shapes.rotation_matrix((0, 0, 1), 90)
    assert np.allclose(got, _transformed(v, f, m), atol=1e-5)


def test_raw_matrix(tmp_path):
    m = np.array([[0, -2, 0, 1], [2, 0, 0, 2], [0, 0, 2, 3], [0, 0, 0, 1]], float)
    rows = ", ".join(str(r.tolist()) for r in m)
    got, _ = _shape_scene(tmp_path, f'type = "sphere"\nmatrix = [{rows}]\n')
    v, f = shapes.ico_sphere(5)
    assert np.allclose(got, _transformed(v, f, m), atol=1e-4)


def test_mirroring_transform_keeps_the_front_side(tmp_path):
    """A negative scale flips the winding; the loader flips it back, so the
    rectangle still faces +z (and a lamp still emits the same way)."""
    _, normals = _shape_scene(tmp_path, 'type = "rectangle"\nscale = [-1, 1, 1]\n')
    assert np.allclose(normals, [0, 0, 1])
    vertices, _ = _shape_scene(tmp_path, 'type = "box"\nscale = [-1, 2, 1]\n')
    v = vertices.reshape(-1, 3)
    box = trimesh.Trimesh(v, np.arange(len(v)).reshape(-1, 3), process=False)
    box.merge_vertices()
    assert box.volume == pytest.approx(16.0)


# -- mesh files ----------------------------------------------------------------

@pytest.mark.parametrize("ext", ["obj", "ply", "stl", "glb"])
def test_mesh_files_load_relative_to_the_scene_file(tmp_path, ext):
    (tmp_path / "meshes").mkdir()
    v, f = shapes.ico_sphere(1)
    trimesh.Trimesh(v, f, process=False).export(str(tmp_path / "meshes" / f"ball.{ext}"))
    got, normals = _shape_scene(tmp_path, f'type = "mesh"\nfile = "meshes/ball.{ext}"\ntranslate = [0, 5, 0]\n')
    assert len(got) == len(f)
    assert np.allclose(got.reshape(-1, 3).mean(0), [0, 5, 0], atol=0.05)
    centroids = got.mean(axis=1) - [0, 5, 0]
    assert np.all(np.sum(normals * centroids, axis=1) > 0)  # still outward


# -- mistakes ------------------------------------------------------------------


MESH_SHAPE = '\n[[shapes]]\ntype = "mesh"\nmaterial = "white"\nfile = "{}"\n'

# (case, scene text, files to create, the key path the message must name)
BAD = {
    "unknown top-level key": ("colour = 1\n" + BASE, {}, "colour"),
    "unknown camera key": (BASE.replace("fov = 40", "fov = 40\nzoom = 2"), {}, "camera.zoom"),
    "unknown material key": (BASE + "\n[materials.x]\ntype = 'diffuse'\ncolour = 1\n", {}, "materials.x.colour"),
    "key unused by the material type": (BASE + "\n[materials.x]\ntype = 'diffuse'\nior = 1.3\n", {}, "materials.x.ior"),
    "unknown material type": (BASE + "\n[materials.x]\ntype = 'velvet'\n", {}, "materials.x.type"),
    "reflectance out of range": (BASE + "\n[materials.x]\ntype = 'diffuse'\nreflectance = 2\n", {},
                                 "materials.x.reflectance"),
    "unknown shape key": (BASE + '\n[[shapes]]\ntype = "box"\nmaterial = "white"\nsize = 2\n', {}, "shapes[1].size"),
    "unknown shape type": (BASE + '\n[[shapes]]\ntype = "cone"\nmaterial = "white"\n', {}, "shapes[1].type"),
    "file on a primitive": (BASE + '\n[[shapes]]\ntype = "box"\nmaterial = "white"\nfile = "a.obj"\n', {},
                            "shapes[1].file"),
    "unknown material": (BASE + '\n[[shapes]]\ntype = "box"\nmaterial = "gold"\n', {}, "shapes[1].material"),
    "shape without material": (BASE + '\n[[shapes]]\ntype = "box"\n', {}, "shapes[1].material"),
    "shapes as a table": (BASE.replace("[[shapes]]", "[shapes]"), {}, "shapes"),
    "missing mesh file": (BASE + MESH_SHAPE.format("nowhere.obj"), {}, "shapes[1].file"),
    "unreadable mesh": (BASE + MESH_SHAPE.format("bad.ply"), {"bad.ply": b"garbage\x00\x01"}, "shapes[1].file"),
    "mesh without triangles": (BASE + MESH_SHAPE.format("empty.obj"), {"empty.obj": b"v 0 0 0\n"}, "shapes[1].file"),
    "NaN vertex": (BASE + MESH_SHAPE.format("nan.obj"), {"nan.obj": b"v 0 0 0\nv 1 0 0\nv nan 1 0\nf 1 2 3\n"},
                   "shapes[1].file"),
    "Inf vertex": (BASE + MESH_SHAPE.format("inf.obj"), {"inf.obj": b"v 0 0 0\nv 1 0 0\nv 0 inf 0\nf 1 2 3\n"},
                   "shapes[1].file"),
    "bad rotate": (BASE.replace("rotate = [1, 0, 0, 90]", "rotate = [1, 0, 90]"), {}, "shapes[0].rotate"),
    "bad rotate in a list": (BASE.replace("rotate = [1, 0, 0, 90]", "rotate = [[1, 0, 0, 90], [0, 0, 0, 5]]"), {},
                             "shapes[0].rotate[1]"),
    "zero scale": (BASE.replace("translate = [0, 2, 0]", "translate = [0, 2, 0]\nscale = [1, 0, 1]"), {},
                   "shapes[0].scale"),
    "matrix with translate": (BASE.replace("rotate = [1, 0, 0, 90]", "matrix = [[1,0,0,0],[0,1,0,0],[0,0,1,0],[0,0,0,1]]"),
                              {}, "shapes[0].matrix"),
    "singular matrix": (BASE.replace("rotate = [1, 0, 0, 90]\ntranslate = [0, 2, 0]",
                                     "matrix = [[1,0,0,0],[0,0,0,0],[0,0,1,0],[0,0,0,1]]"), {}, "shapes[0].matrix"),
    "no light": (BASE.replace('material = "lamp"', 'material = "white"'), {}, "lights"),
    "camera without resolution": (BASE.replace("width = 32\n", ""), {}, "camera.width"),
    "no camera": (BASE[BASE.index("[materials.white]"):], {}, "camera"),
    "fov not a number": (BASE.replace("fov = 40", "fov = '40'"), {}, "camera.fov"),
    "bad fov_axis": (BASE.replace("fov = 40", "fov = 40\nfov_axis = 'diagonal'"), {}, "camera.fov_axis"),
    "zero resolution": (BASE.replace("width = 32", "width = 0"), {}, "camera.width"),
    "unknown light key": (BASE + '\n[[lights]]\ntype = "point"\nposition = [0,1,0]\nintensity = 1\npower = 3\n', {},
                          "lights[0].power"),
    "unknown light type": (BASE + '\n[[lights]]\ntype = "sun"\n', {}, "lights[0].type"),
    "light without position": (BASE + '\n[[lights]]\ntype = "point"\nintensity = 1\n', {}, "lights[0].position"),
    "beam wider than cutoff": (BASE + '\n[[lights]]\ntype = "spot"\nposition = [0,1,0]\ntarget = [0,0,0]\n'
                                      'intensity = 1\ncutoff_angle = 10\nbeam_width = 20\n', {}, "lights[0].beam_width"),
    "render value not plain": (BASE + "\n[render]\niterations = [1, 2]\n", {}, "render.iterations"),
    "render value not finite": (BASE + "\n[render]\nalpha = nan\n", {}, "render.alpha"),
    "invalid TOML": (BASE + "\n[[shapes\n", {}, "invalid TOML"),
    "zero-power light": (BASE.replace("emission = [1, 2, 3]", "emission = 0"), {}, "no light"),
}


@pytest.mark.parametrize("case", BAD)
def test_mistakes_name_the_file_and_the_key(tmp_path, case):
    text, files, key = BAD[case]
    for name, data in files.items():
        (tmp_path / name).write_bytes(data)
    path = _write(tmp_path, text)
    with pytest.raises(SceneError) as info:
        load_toml(path)
    message = str(info.value)
    assert "\n" not in message
    assert message.startswith(path + ":")
    assert key in message, message


def test_missing_scene_file_is_named(tmp_path):
    path = str(tmp_path / "absent.toml")
    with pytest.raises(SceneError, match="absent.toml"):
        load_toml(path)


def test_degenerate_triangles_are_dropped_with_a_warning(tmp_path):
    (tmp_path / "sliver.obj").write_bytes(b"v 0 0 0\nv 1 0 0\nv 2 0 0\nv 0 1 0\nf 1 2 3\nf 1 2 4\n")
    text = BASE + MESH_SHAPE.format("sliver.obj")
    with pytest.warns(UserWarning, match="degenerate"):
        scene = _load(tmp_path, text)
    assert scene.triangle_count == 2 + 1


def test_the_documented_example_loads(tmp_path):
    doc = open(os.path.join(os.path.dirname(EXAMPLE), "..", "docs", "scene-format.md")).read()
    example = doc.split("```toml\n", 1)[1].split("```", 1)[0]
    (tmp_path / "meshes").mkdir()
    knot = os.path.join(os.path.dirname(EXAMPLE), "meshes", "knot.ply")
    (tmp_path / "meshes" / "knot.ply").write_bytes(open(knot, "rb").read())
    scene = _load(tmp_path, example)
    assert sorted(scene.lights.kind.tolist()) == [LIGHT_TRIANGLE] * 2 + [LIGHT_POINT, LIGHT_SPOT]
    assert scene.render_settings == {"iterations": 200, "output": "cornell.exr"}
    assert scene.camera.fov_axis == "smaller"
    m = scene.materials
    lacquer, leaves = m.names.index("lacquer"), m.names.index("leaves")
    assert m.kind[lacquer] == MATERIAL_KINDS["roughplastic"] and m.ior[lacquer] == np.float32(1.49)
    assert m.opacity[leaves] == 0.5 and m.kind[m.names.index("frosted")] == MATERIAL_KINDS["roughdielectric"]
