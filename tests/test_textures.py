"""Textures: the texel lookup against closed forms and Mitsuba 3, UVs
through the loaders, and renders of textured scenes against closed forms,
against the same scene with a constant reflectance, and chunked against
unchunked."""
from __future__ import annotations

import math
import os

import numpy as np
import pytest

from dosppm_core.kernels.texture import lookup_many
from dosppm_core.modes.osppm import OutOfCoreRenderer
from dosppm_core.modes.sppm import Renderer, render
from dosppm_core.scene import builtin
from dosppm_core.scene import textures as tx
from dosppm_core.scene.loaders import load_scene
from dosppm_core.scene.model import Camera, Material, SceneBuilder, SceneError
from dosppm_core.settings import RenderSettings

MITSUBA_DATA = "/work/shared/scenes/mitsuba-data"
SCENES = os.path.join(MITSUBA_DATA, "tests", "scenes")
needs_data = pytest.mark.skipif(not os.path.isdir(SCENES), reason="Mitsuba's test scenes not present")


def _lookup(texture: tx.Texture, u, v) -> np.ndarray:
    table = tx.TextureTable.from_textures([texture])
    return lookup_many(table.info, table.uv_map, table.texels, 0,
                       np.asarray(u, np.float64).ravel(), np.asarray(v, np.float64).ravel())


# -- the lookup ----------------------------------------------------------------------
def test_bilinear_of_a_2x2_texture_is_the_closed_form():
    """Inside the texel centres (1/4 .. 3/4) bilinear filtering of a 2x2
    texture is the bilinear blend of its four texels, texel (x, y) at
    ((x + 1/2) / 2, (y + 1/2) / 2) with y from the top row."""
    c = np.random.default_rng(1).uniform(0, 1, (2, 2, 3)).astype(np.float32)
    u, v = np.random.default_rng(2).uniform(0.25, 0.75, (2, 200))
    a, b = (u - 0.25) * 2, (v - 0.25) * 2
    expected = (((1 - a) * (1 - b))[:, None] * c[0, 0] + (a * (1 - b))[:, None] * c[0, 1]
                + ((1 - a) * b)[:, None] * c[1, 0] + (a * b)[:, None] * c[1, 1])
    got = _lookup(tx.bitmap("t", c, "bilinear", "clamp"), u, v)
    np.testing.assert_allclose(got, expected, rtol=1e-6, atol=1e-7)


@pytest.mark.parametrize("wrap", ["repeat", "mirror", "clamp"])
def test_wrap_modes_pick_the_closed_form_texel(wrap):
    """Nearest lookups of a 3-wide, 1-high ramp at u far outside [0, 1]."""
    ramp = np.array([[[0, 0, 0], [1, 1, 1], [2, 2, 2]]], np.float32)
    u = np.array([-2.9, -1.5, -0.2, 0.1, 0.5, 0.9, 1.1, 1.5, 2.4, 3.7])
    x = np.floor(u * 3).astype(int)
    if wrap == "repeat":
        want = x % 3
    elif wrap == "mirror":
        m = x % 6
        want = np.where(m >= 3, 5 - m, m)
    else:
        want = np.clip(x, 0, 2)
    got = _lookup(tx.bitmap("t", ramp, "nearest", wrap), u, np.full_like(u, 0.5))
    np.testing.assert_array_equal(got[:, 0], want)


def test_checkerboard_and_to_uv():
    """color0 where both fractional parts lie on the same side of 1/2;
    to_uv scales (u, v) first."""
    board = tx.checkerboard("c", (1, 0, 0), (0, 0, 1), (4.0, 0.0, 0.0, 0.0, 4.0, 0.0))
    u, v = np.random.default_rng(3).uniform(-1, 1, (2, 300))
    same = ((4 * u) % 1 > 0.5) == ((4 * v) % 1 > 0.5)
    got = _lookup(board, u, v)
    np.testing.assert_array_equal(got[:, 0], same.astype(float))
    np.testing.assert_array_equal(got[:, 2], (~same).astype(float))


def test_8bit_images_are_srgb_decoded_unless_raw(tmp_path):
    from PIL import Image
    levels = np.arange(0, 256, 17, dtype=np.uint8)
    img = np.stack([levels, levels[::-1], np.full_like(levels, 128)], -1)[None]   # (1, 16, 3)
    Image.fromarray(img).save(tmp_path / "t.png")
    c = img.astype(np.float64) / 255
    srgb = np.where(c <= 0.04045, c / 12.92, ((c + 0.055) / 1.055) ** 2.4)
    np.testing.assert_allclose(tx.read_image(str(tmp_path / "t.png")), srgb, rtol=1e-6)
    np.testing.assert_allclose(tx.read_image(str(tmp_path / "t.png"), raw=True), c, rtol=1e-6)
    Image.fromarray(img[0, :, 0][None]).save(tmp_path / "g.png")        # greyscale: 3 equal channels
    grey = tx.read_image(str(tmp_path / "g.png"))
    np.testing.assert_allclose(grey, np.repeat(srgb[:, :, :1], 3, axis=2), rtol=1e-6)


def test_exr_texels_are_linear(tmp_path):
    from dosppm_core.film import write_exr
    rgb = np.random.default_rng(4).uniform(0, 3, (3, 5, 3)).astype(np.float32)
    write_exr(str(tmp_path / "t.exr"), rgb)
    np.testing.assert_array_equal(tx.read_image(str(tmp_path / "t.exr")), rgb)


@pytest.mark.reference
@pytest.mark.parametrize("filter_type", ["bilinear", "nearest"])
@pytest.mark.parametrize("wrap", ["repeat", "mirror", "clamp"])
def test_lookup_matches_mitsuba(tmp_path, filter_type, wrap, mi):
    """Our lookup of an 8-bit PNG against Mitsuba 3's `bitmap` eval, at
    coordinates inside and far outside [0, 1]."""
    from PIL import Image
    img = np.random.default_rng(5).integers(0, 256, (3, 5, 3), dtype=np.uint8)
    Image.fromarray(img).save(tmp_path / "t.png")
    ours = tx.bitmap("t", tx.read_image(str(tmp_path / "t.png")), filter_type, wrap)
    theirs = mi.load_dict({"type": "bitmap", "filename": str(tmp_path / "t.png"),
                           "filter_type": filter_type, "wrap_mode": wrap})
    uv = np.random.default_rng(6).uniform(-2.3, 2.7, (40, 2))
    got = _lookup(ours, uv[:, 0], uv[:, 1])
    si = mi.SurfaceInteraction3f()
    for (u, v), value in zip(uv, got):
        si.uv = mi.Point2f(u, v)
        np.testing.assert_allclose(value, np.array(theirs.eval(si)), rtol=1e-4, atol=1e-5)


# -- UVs through the loaders ------------------------------------------------------------
def _mitsuba_uv(shape: dict, origins, directions):
    mi = pytest.importorskip("mitsuba")
    mi.set_variant("scalar_rgb")
    scene = mi.load_dict({"type": "scene", "s": shape})
    out = []
    for o, d in zip(origins, directions):
        si = scene.ray_intersect(mi.Ray3f(mi.Point3f(*o), mi.Vector3f(*d)))
        out.append(np.array(si.uv) if si.is_valid() else (np.nan, np.nan))
    return np.array(out)


def _our_uv(scene, origins, directions):
    from dosppm_core.accel import Accelerator
    accel = Accelerator(scene.vertices, scene.triangles)
    prim, _t, u, v = accel.intersect(np.asarray(origins, np.float32), np.asarray(directions, np.float32))
    accel.close()
    corners = scene.uvs[scene.triangles[prim]].astype(np.float64)
    w = (1 - u - v)[:, None]
    return np.where((prim >= 0)[:, None], w * corners[:, 0] + u[:, None] * corners[:, 1]
                    + v[:, None] * corners[:, 2], np.nan)


def _textured_shape_xml(tmp_path, shape_xml: str) -> str:
    from PIL import Image
    Image.fromarray(np.zeros((2, 2, 3), np.uint8)).save(tmp_path / "t.png")
    path = tmp_path / "s.xml"
    path.write_text(f"""<scene version="3.0.0">
  <sensor type="perspective"><transform name="to_world"><lookat origin="0,0,9" target="0,0,0" up="0,1,0"/>
  </transform><film type="hdrfilm"><integer name="width" value="8"/><integer name="height" value="8"/></film></sensor>
  <emitter type="point"><point name="position" x="0" y="0" z="5"/><rgb name="intensity" value="1"/></emitter>
  {shape_xml.replace("BSDF", '<bsdf type="diffuse"><texture type="bitmap" name="reflectance">'
                     '<string name="filename" value="t.png"/></texture></bsdf>')}
</scene>""")
    return str(path)


def _rays_at(directions_to):
    """Rays from 5 units out toward the origin-side points given (p, d)."""
    p, d = directions_to
    d = np.asarray(d, np.float64)
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    return np.asarray(p) - 5 * d, d


def _shape_rays(kind: str):
    rng = np.random.default_rng(7)
    if kind in ("rectangle", "obj", "ply"):
        p = np.c_[rng.uniform(-0.95, 0.95, (30, 2)), np.zeros(30)]
        return _rays_at((p, np.tile([0, 0, -1.0], (30, 1))))
    if kind == "disk":
        r, phi = np.sqrt(rng.uniform(0.05, 0.9, 30)), rng.uniform(0.05, 2 * np.pi - 0.05, 30)
        p = np.c_[r * np.cos(phi), r * np.sin(phi), np.zeros(30)]
        return _rays_at((p, np.tile([0, 0, -1.0], (30, 1))))
    if kind == "cylinder":
        phi, z = rng.uniform(0.05, 2 * np.pi - 0.05, 30), rng.uniform(0.05, 0.95, 30)
        p = np.c_[np.cos(phi), np.sin(phi), z]
        return _rays_at((p, -np.c_[np.cos(phi), np.sin(phi), np.zeros(30)]))
    if kind == "sphere":
        phi, ct = rng.uniform(0.05, 2 * np.pi - 0.05, 30), rng.uniform(-0.95, 0.95, 30)
        st = np.sqrt(1 - ct * ct)
        p = np.c_[st * np.cos(phi), st * np.sin(phi), ct]
        return _rays_at((p, -p))
    # cube: a point on each face, away from the edges
    faces = []
    for axis in range(3):
        for side in (-1.0, 1.0):
            for _ in range(5):
                q = rng.uniform(-0.9, 0.9, 3)
                q[axis] = side
                d = np.zeros(3)
                d[axis] = -side
                faces.append((q, d))
    return _rays_at((np.array([f[0] for f in faces]), np.array([f[1] for f in faces])))


@pytest.mark.reference
@pytest.mark.parametrize("kind", ["rectangle", "cube", "sphere", "disk", "cylinder", "obj", "ply"])
def test_shape_uvs_match_mitsuba(tmp_path, kind):
    """The texture coordinate at ray hits on each shape, ours (interpolated
    from the vertices) against Mitsuba's (analytic, or its mesh readers')."""
    pytest.importorskip("mitsuba")
    shape = {"type": kind}
    if kind == "obj":
        if not os.path.isdir(MITSUBA_DATA):
            pytest.skip("Mitsuba's test data not present")
        shape["filename"] = os.path.join(MITSUBA_DATA, "common", "meshes", "rectangle.obj")
    elif kind == "ply":
        (tmp_path / "r.ply").write_text(
            "ply\nformat ascii 1.0\nelement vertex 4\nproperty float x\nproperty float y\nproperty float z\n"
            "property float u\nproperty float v\nelement face 2\nproperty list uchar int vertex_indices\n"
            "end_header\n-1 -1 0 0 0.2\n1 -1 0 0.9 0\n1 1 0 1 1\n-1 1 0 0.1 0.7\n3 0 1 2\n3 0 2 3\n")
        shape["filename"] = str(tmp_path / "r.ply")
    extra = "".join(f'<string name="filename" value="{shape["filename"]}"/>' for _ in [0] if "filename" in shape)
    scene = load_scene(_textured_shape_xml(tmp_path, f'<shape type="{kind}">{extra}BSDF</shape>'))
    o, d = _shape_rays(kind)
    ours, theirs = _our_uv(scene, o, d), _mitsuba_uv(shape, o, d)
    assert not np.any(np.isnan(theirs)) and not np.any(np.isnan(ours))
    # Spheres, disks and cylinders are polygons here: the hit moves a little.
    np.testing.assert_allclose(ours, theirs, atol=3e-3 if kind in ("sphere", "disk", "cylinder") else 1e-5)


@pytest.mark.reference
def test_tilted_cylinder_uvs_match_mitsuba(tmp_path):
    """A cylinder from p0 to p1: u starts where Mitsuba's frame of the axis
    puts phi = 0 (compared modulo 1, the seam being anywhere), v runs 0..1
    from p0 to p1."""
    pytest.importorskip("mitsuba")
    p0, p1, radius = np.array([0.2, -0.1, 0.3]), np.array([0.5, 0.8, -0.4]), 0.7
    xml = (f'<shape type="cylinder"><point name="p0" value="{",".join(map(str, p0))}"/>'
           f'<point name="p1" value="{",".join(map(str, p1))}"/><float name="radius" value="{radius}"/>BSDF</shape>')
    scene = load_scene(_textured_shape_xml(tmp_path, xml))
    axis = p1 - p0
    e1 = np.cross(axis, [1.0, 0.0, 0.0])
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(axis / np.linalg.norm(axis), e1)
    rng = np.random.default_rng(8)
    phi, t = rng.uniform(0, 2 * np.pi, 30), rng.uniform(0.05, 0.95, 30)
    radial = np.cos(phi)[:, None] * e1 + np.sin(phi)[:, None] * e2
    points = p0 + t[:, None] * axis + radius * radial
    o, d = points + 5 * radial, -radial
    ours = _our_uv(scene, o, d)
    theirs = _mitsuba_uv({"type": "cylinder", "p0": mi_point(p0), "p1": mi_point(p1), "radius": radius}, o, d)
    du = np.abs(ours[:, 0] - theirs[:, 0]) % 1.0
    assert np.all(np.minimum(du, 1 - du) < 3e-3), np.c_[ours[:, 0], theirs[:, 0]]
    np.testing.assert_allclose(ours[:, 1], theirs[:, 1], atol=1e-4)


def mi_point(p):
    import mitsuba as mi
    return mi.ScalarPoint3f(*map(float, p))


def test_untextured_shapes_store_no_uvs(tmp_path):
    path = _textured_shape_xml(tmp_path, '<shape type="sphere"><bsdf type="diffuse"/></shape>')
    scene = load_scene(path)
    assert scene.uvs.shape == (0, 2) and len(scene.textures) == 0
    assert scene.materials.texture.tolist() == [-1]


@needs_data
def test_mitsuba_texture_interp_scene_loads():
    scene = load_scene(os.path.join(SCENES, "texture_interp", "test_texture_interp_direct.xml"))
    t = scene.textures
    assert len(t) == 6 and scene.materials.texture.tolist() == list(range(6))
    # (filter, wrap) in the file's order; to_uv = translate(-1/2) * scale(2).
    assert t.info[:, tx.INFO_FILTER].tolist() == [0, 0, 0, 1, 1, 1]
    assert t.info[:, tx.INFO_WRAP].tolist() == [0, 1, 2, 0, 1, 2]
    np.testing.assert_allclose(t.uv_map, np.tile([2, 0, -0.5, 0, 2, -0.5], (6, 1)))
    assert t.info[0, tx.INFO_WIDTH] > 1 and scene.uvs.shape == (len(scene.vertices), 2)
    # One image file, one texel block, shared by the six textures (and by a chunk's subset).
    assert len(t.texels) == t.info[0, tx.INFO_WIDTH] * t.info[0, tx.INFO_HEIGHT]
    assert not t.info[:, tx.INFO_OFFSET].any()
    sub, remap = t.subset([1, 4])
    assert len(sub.texels) == len(t.texels) and remap.tolist() == [-1, 0, -1, -1, 1, -1]


@pytest.mark.reference
def test_the_reference_export_refuses_a_textured_material():
    """Its reflectance row is (1, 1, 1): exporting it would render another scene."""
    pytest.importorskip("mitsuba")
    from harness import reference
    with pytest.raises(SceneError, match="'white': a textured material has no Mitsuba mapping"):
        reference.scene_to_mitsuba_dict(_checker_box(), 4)


def test_a_texture_on_an_unread_parameter_is_refused(tmp_path):
    # (A rough conductor reads a textured alpha since issue 33's anisotropy; a rough dielectric does not.)
    path = _textured_shape_xml(tmp_path, '<shape type="rectangle"><bsdf type="roughdielectric">'
                               '<string name="distribution" value="ggx"/>'
                               '<texture type="checkerboard" name="alpha"/></bsdf></shape>')
    with pytest.raises(SceneError, match=r"s\.xml:\d+: <texture type=\"checkerboard\" name=\"alpha\">: "
                       r"not allowed inside <bsdf type=\"roughdielectric\">"):
        load_scene(path)


# -- renders ---------------------------------------------------------------------------
QUADRANTS = np.array([[[0.8, 0.1, 0.1], [0.1, 0.8, 0.1]], [[0.1, 0.1, 0.8], [0.7, 0.7, 0.7]]], np.float32)
SIZE = 24


def _plane(texture: tx.Texture | None, light=(0.3, -0.2, 1.0), intensity=2.0, rho=None):
    """A large diffuse plane z = 0 with uv = (x, y) + 1/2, one point light
    above it, the camera between them looking down (as tests/test_direct)."""
    b = SceneBuilder(name="plane")
    if texture is not None:
        b.add_material(Material("floor", "diffuse", texture=b.add_texture(texture), two_sided=False))
    else:
        b.add_material(Material("floor", "diffuse", rho, two_sided=False))
    big = 20.0
    v = np.array([[-big, -big, 0], [big, -big, 0], [big, big, 0], [-big, big, 0]], float)
    b.add_mesh(v, [(0, 1, 2), (0, 2, 3)], "floor", "floor", uv=v[:, :2] + 0.5)
    b.add_point_light(light, (intensity,) * 3, "lamp")
    b.camera = Camera((0, 0, 0.8), (0, 0, 0), (0, 1, 0), 70, SIZE, SIZE)
    return b.build()


def _pixel_points(scene, sub: int = 8) -> np.ndarray:
    """Where eye rays through a sub x sub grid in each pixel meet z = 0."""
    f = scene.camera.frame()
    pos, right, up, fwd, (tx_, ty) = f[0], f[1], f[2], f[3], f[4, :2]
    offs = (np.arange(sub) + 0.5) / sub
    cols = (2.0 * (np.arange(SIZE)[:, None] + offs[None, :]) / SIZE - 1.0) * tx_
    rows = (1.0 - 2.0 * (np.arange(SIZE)[:, None] + offs[None, :]) / SIZE) * ty
    d = fwd + cols[None, :, None, :, None] * right + rows[:, None, :, None, None] * up
    t = -pos[2] / d[..., 2]
    return (pos + t[..., None] * d).reshape(SIZE, SIZE, sub * sub, 3)


def test_textured_plane_radiance_is_texel_irradiance_over_pi():
    """Each pixel's radiance is texel(x) E(x) / pi with E from the point
    light in closed form and the texel of a nearest-filtered 2x2 texture
    (one colour per quadrant of the view); pixels that straddle two texels
    are left out."""
    light, intensity = np.array([0.3, -0.2, 1.0]), 2.0
    scene = _plane(tx.bitmap("quadrants", QUADRANTS, "nearest"), light, intensity)
    x = _pixel_points(scene)
    d = light - x
    dist = np.linalg.norm(d, axis=-1)
    irradiance = intensity * (d[..., 2] / dist) / dist ** 2
    u, v = x[..., 0] + 0.5, x[..., 1] + 0.5
    col, row = np.floor(u * 2).astype(int) % 2, np.floor(v * 2).astype(int) % 2
    texel = QUADRANTS[row, col]                                     # (H, W, sub, 3)
    expected = (texel * irradiance[..., None] / math.pi).mean(2)
    one_texel = np.all(texel == texel[:, :, :1], axis=(2, 3))
    got = render(scene, RenderSettings(photons_per_iteration=10_000), iterations=64)
    assert one_texel.sum() > 0.8 * SIZE * SIZE
    np.testing.assert_allclose(got[one_texel], expected[one_texel], rtol=0.01)
    # Without the texture the same pixels would be far off: the test can fail.
    assert np.abs(got[one_texel] / expected[one_texel] - 1).max() < 0.01


def _with_textured_material(scene, name, texture, uv_of=None):
    """`scene` with material `name`'s reflectance read from `texture`
    instead (or each of several names from its texture), every vertex
    given uv_of(vertices) (default (0, 0))."""
    names, textures = ([name], [texture]) if isinstance(name, str) else (name, texture)
    m = scene.materials
    m.texture = np.full(len(m.kind), -1, np.int32)
    m.reflectance = m.reflectance.copy()
    for t, n in enumerate(names):
        m.texture[m.names.index(n)] = t
        m.reflectance[m.names.index(n)] = 1.0
    scene.textures = tx.TextureTable.from_textures(textures)
    uv = np.zeros((len(scene.vertices), 2)) if uv_of is None else uv_of(scene.vertices.astype(np.float64))
    scene.uvs = uv.astype(np.float32)
    return scene


def _small(name="cornell-box", size=32):
    scene = builtin.make(name)
    scene.camera.width = scene.camera.height = size
    return scene


def _render_iterations(scene, iterations=3, **kw):
    r = Renderer(scene, RenderSettings(seed=11, photons_per_iteration=30_000, **kw))
    try:
        for _ in range(iterations):
            r.run_iteration()
        return r.image()
    finally:
        r.close()


@pytest.mark.parametrize("material", ["white", "red"])
def test_constant_texture_renders_the_constant_reflectance(material):
    """A 1x1 nearest texture of a material's own colour renders the same
    image as the constant, seed for seed: photons (roulette on the texel),
    hit points (the texel in their weight), the gather and the shadow rays
    all read it. Only float rounding of weight x texel may differ."""
    plain = _render_iterations(_small())
    colour = _small().materials.reflectance[_small().materials.names.index(material)]
    textured = _with_textured_material(_small(), material, tx.bitmap("c", colour.reshape(1, 1, 3), "nearest"))
    assert textured.materials.textured
    img = _render_iterations(textured)
    np.testing.assert_allclose(img, plain, rtol=1e-4, atol=1e-6 * plain.max())
    # A different colour changes the image: the texture is really read.
    dim = _with_textured_material(_small(), material, tx.bitmap("c", 0.5 * colour.reshape(1, 1, 3), "nearest"))
    changed = np.abs(_render_iterations(dim) - plain) > 0.1 * plain
    assert np.mean(np.any(changed, axis=2)) > 0.05


def _checker_box():
    """The Cornell box with its white surfaces checkered (squares of 100
    mm), its red and green walls bilinear gradients of their colours (uv
    from the vertices' positions)."""
    scene = _small("cornell-box", 32)
    board = tx.checkerboard("board", (0.9, 0.9, 0.9), (0.1, 0.1, 0.4),
                            (1 / 100, 0.0, 0.0, 0.0, 1 / 100, 0.0))
    ramp = np.linspace(0.2, 1.0, 8)[None, :, None]
    red = tx.bitmap("red", ramp * [0.6, 0.05, 0.05], uv_map=(0.0, 0.0, 0.0, 1 / 560, 0.0, 0.0))
    green = tx.bitmap("green", ramp * [0.1, 0.4, 0.08], uv_map=(0.0, 0.0, 0.0, 1 / 560, 0.0, 0.0))
    return _with_textured_material(scene, ["white", "red", "green"], [board, red, green],
                                   lambda v: np.c_[v[:, 0] + v[:, 2], v[:, 1]])


def test_textured_scene_chunked_equals_unchunked(chunk_store):
    """The real subdivider into 4 chunks (UVs and textures in the chunk
    files), OSPPM from the store: the unchunked image up to float noise."""
    scene = _checker_box()
    settings = RenderSettings(seed=11, photons_per_iteration=30_000)
    ref = _render_iterations(scene)
    store = chunk_store(scene, chunks=4)
    assert store.chunk_count == 4
    assert len(store.header.textures) == 3 and len(store.header.textures.texels) == 0
    o = OutOfCoreRenderer(store, settings, pipelined=False)
    try:
        for _ in range(3):
            o.run_iteration()
        img = o.image()
    finally:
        o.close()
    rel = np.abs(img - ref) / np.maximum(ref, 1e-6 * ref.max())
    assert np.mean(rel > 1e-4) < 0.02 and rel.max() < 0.01
    plain = _render_iterations(_small("cornell-box", 32))
    assert np.mean(np.abs(plain - ref) > 0.1 * plain) > 0.1      # the checkerboard shows


def test_a_chunk_carries_only_its_textures_in_its_checked_file(chunk_store):
    """Each chunk file holds the textures its triangles' materials read,
    no others; their bytes count in its memory estimate; a damaged texel
    fails the chunk's checksum like any of its bytes."""
    from dosppm_core.chunks.store import StoreError
    from dosppm_core.chunks.subdivide import chunk_memory_bytes
    scene = _checker_box()
    store = chunk_store(scene, chunks=4)
    carried = []
    for k in range(store.chunk_count):
        g = store.load(k)
        used = scene.materials.texture[np.unique(g.tri_material)]
        assert sorted(g.tex_ids.tolist()) == sorted(set(used[used >= 0].tolist()))
        for j, t in enumerate(g.tex_ids):       # the very texels of the scene's table
            a, w, h = scene.textures.info[t, 1:4]
            b, bw, bh = g.tex_info[j, 1:4]
            np.testing.assert_array_equal(g.texels[b:b + bw * bh], scene.textures.texels[a:a + w * h])
        assert store.chunk_memory[k] == chunk_memory_bytes(len(g.triangles), len(g.vertices), True) \
            + g.texture_bytes
        carried.append(len(g.tex_ids))
    assert min(carried) < 3                     # some chunk leaves a texture out
    k = int(np.argmax(carried))
    entry = store.manifest["chunks"][k]
    path = os.path.join(store.path, entry["file"])
    with open(path, "r+b") as f:
        f.seek(entry["arrays"]["texels"][0] + 4)
        byte = f.read(1)
        f.seek(-1, 1)
        f.write(bytes([byte[0] ^ 0x40]))
    with pytest.raises(StoreError, match="checksum mismatch"):
        store.load(k)


GI_SCENE = """<scene version="3.0.0">
  <integrator type="path"><integer name="max_depth" value="-1"/></integrator>
  <sensor type="perspective">
    <float name="fov" value="50"/>
    <transform name="to_world"><lookat origin="0, 1.2, 3.2" target="0, 0.6, 0" up="0, 1, 0"/></transform>
    <film type="hdrfilm"><integer name="width" value="48"/><integer name="height" value="48"/>
      <rfilter type="box"/></film>
  </sensor>
  <shape type="rectangle">
    <transform name="to_world"><rotate x="1" angle="-90"/><scale value="2"/></transform>
    <bsdf type="diffuse">
      <texture type="checkerboard" name="reflectance">
        <rgb name="color0" value="0.9, 0.15, 0.1"/><rgb name="color1" value="0.05, 0.1, 0.7"/>
        <transform name="to_uv"><scale value="3"/></transform>
      </texture>
    </bsdf>
  </shape>
  <shape type="rectangle">
    <transform name="to_world"><scale value="2"/><translate y="2" z="-1.5"/></transform>
    <bsdf type="diffuse"><rgb name="reflectance" value="0.8"/></bsdf>
  </shape>
  <shape type="rectangle">
    <transform name="to_world"><rotate x="1" angle="90"/><scale value="0.3"/><translate y="2.2" z="0.5"/></transform>
    <emitter type="area"><rgb name="radiance" value="20"/></emitter>
  </shape>
</scene>"""


@pytest.mark.reference
def test_light_off_a_textured_floor_matches_mitsuba(tmp_path, mi):
    """A checkered floor (red and blue squares) lights a white wall: the
    wall's indirect light comes through photons that bounced off the floor,
    so it is right only if photons read the texel where they land. Ours
    (SPPM) against Mitsuba's path tracer, per 8x8-pixel block."""
    path = tmp_path / "gi.xml"
    path.write_text(GI_SCENE)
    theirs = np.array(mi.render(mi.load_file(str(path)), spp=512))
    ours = render(load_scene(str(path)), RenderSettings(seed=3, photons_per_iteration=50_000), iterations=100)

    def blocks(img):
        return img.reshape(6, 8, 6, 8, 3).mean((1, 3))
    np.testing.assert_allclose(ours.mean((0, 1)), theirs.mean((0, 1)), rtol=0.01)
    np.testing.assert_allclose(blocks(ours), blocks(theirs), rtol=0.04, atol=1e-3)


def test_a_tracer_without_the_store_fetches_a_chunks_textures_with_it(chunk_store, tmp_path):
    """A tracer on another node fetches chunk files by id (services.tracer.fetch):
    the textures come in the same file, under the same SHA-256 check."""
    from types import SimpleNamespace

    from dosppm_core.chunks.store import StoreError
    from services.tracer.fetch import FetchedStore
    store = chunk_store(_checker_box(), chunks=4)
    k = int(np.argmax([e.get("textures", 0) for e in store.manifest["chunks"]]))
    entry = store.manifest["chunks"][k]
    with open(os.path.join(store.path, entry["file"]), "rb") as f:
        data = bytearray(f.read())

    def serve(chunk):
        return [SimpleNamespace(sha256=entry["sha256"], file_bytes=len(data), offset=0,
                                data=np.frombuffer(bytes(data), np.uint8))]
    fetched = FetchedStore(store.manifest, str(tmp_path / "node"), serve).load(k)
    there = store.load(k)
    assert len(fetched.tex_ids) > 0
    for name in ("tex_ids", "tex_info", "tex_uv", "texels", "uv"):
        np.testing.assert_array_equal(getattr(fetched, name), getattr(there, name))
    data[entry["arrays"]["texels"][0]] ^= 0x01          # one damaged texel in transit
    with pytest.raises(StoreError, match="fails its SHA-256 check"):
        FetchedStore(store.manifest, str(tmp_path / "other"), serve).load(k)


@needs_data
def test_mitsubas_textured_diffuse_sphere_matches_its_reference():
    """bsdf_spheres/test_textured_diffuse: sphere.obj's UVs (v flipped as
    Mitsuba's OBJ reader does) and wood.jpg (sRGB-decoded, bilinear) under
    the museum envmap, against Mitsuba's own reference image. Its
    max_depth 2 (camera ray and one bounce: direct light) is our 1."""
    from dosppm_core.film import read_exr
    folder = os.path.join(SCENES, "bsdf_spheres")
    scene = load_scene(os.path.join(folder, "test_textured_diffuse_path.xml"))
    assert len(scene.textures) == 1 and scene.textures.info[0, tx.INFO_WIDTH] == 2048
    ours = render(scene, RenderSettings(seed=1, photons_per_iteration=20_000, max_depth=1), iterations=200)
    ref, _ = read_exr(os.path.join(folder, "refs", "test_textured_diffuse_ref_rgb.exr"))

    def blocks(img):
        return img.reshape(6, 8, 6, 8, 3).mean((1, 3))
    np.testing.assert_allclose(ours.mean((0, 1)), ref.mean((0, 1)), rtol=0.01)
    np.testing.assert_allclose(blocks(ours), blocks(ref), rtol=0.03, atol=1e-3)


@pytest.mark.parametrize("element", ["vertex", "face"])
def test_mesh_attribute_layout_gives_mitsubas_interpolation(element):
    """A per-vertex attribute laid out as 2x2 bilinear blocks is the
    barycentric interpolation of the corners' values inside every
    triangle; a per-face one is the face's value."""
    from dosppm_core.scene.mitsuba.attributes import per_triangle
    rng = np.random.default_rng(9)
    vertices = rng.uniform(-1, 1, (7, 3))
    faces = np.array([[0, 1, 2], [2, 3, 4], [4, 5, 6], [6, 0, 3], [1, 5, 3]])
    values = rng.uniform(0, 1, (7 if element == "vertex" else 5, 3))
    _v, f, uv, texture = per_triangle(element, values, vertices, faces)
    b1, b2 = rng.uniform(0, 1, (2, 400))
    b1, b2 = np.where(b1 + b2 > 1, 1 - b1, b1), np.where(b1 + b2 > 1, 1 - b2, b2)
    tri = rng.integers(0, len(faces), 400)
    corners = uv[f[tri]]
    at = (1 - b1 - b2)[:, None] * corners[:, 0] + b1[:, None] * corners[:, 1] + b2[:, None] * corners[:, 2]
    got = _lookup(texture, at[:, 0], at[:, 1])
    if element == "vertex":
        c = values[faces[tri]]
        want = (1 - b1 - b2)[:, None] * c[:, 0] + b1[:, None] * c[:, 1] + b2[:, None] * c[:, 2]
    else:
        want = values[tri]
    np.testing.assert_allclose(got, want, rtol=1e-4, atol=1e-5)


@needs_data
@pytest.mark.parametrize("name", ["test_mesh_attributes_3_face", "test_mesh_attributes_3_vertex"])
def test_mitsubas_mesh_attribute_scenes_match_their_references(name):
    """A PLY sphere coloured by its face or vertex colours under a
    directional light (Mitsuba's direct integrator: our max_depth 1)."""
    from dosppm_core.film import read_exr
    folder = os.path.join(SCENES, "mesh_attributes")
    scene = load_scene(os.path.join(folder, f"{name}_direct.xml"))
    ours = render(scene, RenderSettings(seed=1, photons_per_iteration=20_000, max_depth=1), iterations=100)
    ref, _ = read_exr(os.path.join(folder, "refs", f"{name}_ref_rgb.exr"))

    def blocks(img):
        return img.reshape(6, 8, 6, 8, 3).mean((1, 3))
    np.testing.assert_allclose(ours.mean((0, 1)), ref.mean((0, 1)), rtol=0.01)
    np.testing.assert_allclose(blocks(ours), blocks(ref), rtol=0.05, atol=1e-4)
