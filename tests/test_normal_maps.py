"""Mitsuba 3's normalmap and bumpmap (kernels.shading): the perturbed
normal against Mitsuba's own BSDF evaluation, a flat map equal to no map
bit for bit, a tilted one's closed form, and the scenes that use them."""
import math
import os

import numpy as np
import pytest

import dosppm_core as dp
from dosppm_core.kernels.materials import bsdf_rows, hit_point_eval
from dosppm_core.kernels.shading import shading_normal, terminator
from dosppm_core.scene.mitsuba import load_mitsuba_xml
from dosppm_core.scene.model import MATERIAL_KINDS, Material, MaterialTable
from dosppm_core.scene.textures import TextureTable, bitmap
from tests.helpers.renders import (
    assert_equal_up_to_float_noise,
    floor_and_wall,
    one_triangle_chunk,
    sppm_and_osppm_images,
)

SIDE = 2.0      # the triangle's legs: dp/du = SIDE * s, so a bump's gradient is scaled as Mitsuba scales it


def _rotation(rng):
    q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    return q * np.sign(np.linalg.det(q))


def _triangle(rot):
    """One triangle of legs SIDE along the rotated x and y axes, uv (0,0) (1,0) (0,1)."""
    verts = (np.array([[0, 0, 0], [SIDE, 0, 0], [0, SIDE, 0]], np.float64) @ rot.T).astype(np.float32)
    uvs = np.array([[0, 0], [1, 0], [0, 1]], np.float32)
    return verts, np.array([[0, 1, 2]], np.int32), uvs


def _ours(material, texture, rot, uv, wi):
    """(perturbed normal, a2) of the material at uv of the rotated triangle, seen from wi."""
    verts, tris, uvs = _triangle(rot)
    table = TextureTable.from_textures([texture])
    rows = bsdf_rows(MaterialTable.from_materials([material]))
    n = np.asarray(verts[1] - verts[0], np.float64)
    n = np.cross(n, np.asarray(verts[2] - verts[0], np.float64))
    n /= np.linalg.norm(n)
    s0, s1, s2, a2 = shading_normal(rows, 0, verts, (uvs, tris, table.info, table.uv_map, table.texels), 0,
                                    uv[0], uv[1], n[0], n[1], n[2], True, wi[0], wi[1], wi[2], True)
    return np.array([s0, s1, s2]), a2, n


def _mitsuba_value(mi, bsdf, rot, uv, wi, wo):
    """Mitsuba's eval (f cos) at a surface point whose frame and dp/du, dp/dv are the triangle's."""
    si = mi.SurfaceInteraction3f()
    s, t, n = (mi.Vector3f(*map(float, rot[:, k])) for k in range(3))
    si.sh_frame = mi.Frame3f(s, t, n)
    si.n = n
    si.dp_du, si.dp_dv = SIDE * s, SIDE * t
    si.uv = mi.Point2f(*map(float, uv))
    si.wi = si.to_local(mi.Vector3f(*map(float, wi)))
    value = bsdf.eval(mi.BSDFContext(), si, si.to_local(mi.Vector3f(*map(float, wo))))
    return float(np.asarray(value)[0])


def _our_value(ns, a2, n, wi, wo, material=None):
    """The nested BSDF at ns (f cos, red channel), with Mitsuba's side
    tests and shadowing term: the diffuse's, or a coloured kind's
    hit-point evaluation (`kernels.materials`)."""
    if not (np.dot(wi, ns) > 0 and np.dot(wo, ns) > 0 and np.dot(wo, n) > 0):
        return 0.0
    if material is None:
        f = 0.5 / math.pi
    else:
        row = bsdf_rows(MaterialTable.from_materials([material]))[0]
        kind = MATERIAL_KINDS[material.kind]
        f = hit_point_eval(kind, row, *ns, *wi, *wo)[0]
    return f * np.dot(wo, ns) * terminator(a2, np.dot(wo, n))


def _directions(rng, rot):
    """Eye and light directions above the surface, some of them grazing."""
    out = []
    for _ in range(2):
        d = rng.normal(size=3)
        d /= np.linalg.norm(d)
        d[2] = abs(d[2]) * (0.05 if rng.random() < 0.3 else 1.0)
        out.append(rot @ (d / np.linalg.norm(d)))
    return out


# Nested BSDFs: (Mitsuba's dict, our material or None for the diffuse).
NESTED = {
    "diffuse": ({"type": "diffuse", "reflectance": {"type": "rgb", "value": 0.5}}, None),
    "roughconductor": ({"type": "roughconductor", "distribution": "ggx", "alpha": 0.3,
                        "eta": {"type": "rgb", "value": 0.2}, "k": {"type": "rgb", "value": 3.0}},
                       Material("rc", "roughconductor", (1, 1, 1), roughness=0.3, distribution="ggx",
                                conductor_eta=(0.2,) * 3, conductor_k=(3.0,) * 3, two_sided=False)),
    "roughplastic": ({"type": "roughplastic", "distribution": "beckmann", "alpha": 0.2,
                      "diffuse_reflectance": {"type": "rgb", "value": 0.4}},
                     Material("rp", "roughplastic", (0.4,) * 3, roughness=0.2, distribution="beckmann",
                              ior=1.49 / 1.000277, two_sided=False)),
}


@pytest.mark.reference
@pytest.mark.parametrize("nested", list(NESTED))
def test_normal_map_matches_mitsuba(mi, nested):
    """Random tilted normals, frames and directions (a third grazing, so
    that flip_invalid_normals acts): our perturbed normal in the nested
    BSDF, with the side tests and the shadowing term, equals Mitsuba's
    normalmap eval."""
    rng = np.random.default_rng(4)
    flips = 0
    their_bsdf, ours = NESTED[nested]
    for _ in range(200):
        rot = _rotation(rng)
        c = np.clip(0.5 + 0.5 * np.array([*rng.normal(scale=0.5, size=2), 1.0]), 0, 1)
        c[2] = max(c[2], 0.55)
        texture = bitmap("n", c.reshape(1, 1, 3), "nearest")
        wi, wo = _directions(rng, rot)
        uv = rng.random(2) * 0.5
        ns, a2, n = _ours(Material("m", normal_map=0), texture, rot, uv, wi)
        bsdf = mi.load_dict({"type": "normalmap", "normalmap": {"type": "rawconstant", "value": c.tolist()},
                             "bsdf": their_bsdf})
        theirs = _mitsuba_value(mi, bsdf, rot, uv, wi, wo)
        local = np.array([np.dot(ns, rot[:, 0]), np.dot(ns, rot[:, 1])])
        flips += np.dot(local, (2 * c - 1)[:2]) < 0
        assert _our_value(ns, a2, n, wi, wo, ours) == pytest.approx(theirs, rel=2e-4, abs=1e-6)
    assert flips > 5        # the flip was exercised


@pytest.mark.reference
def test_bump_map_matches_mitsuba(mi):
    """A random 5x4 height field, bilinear, under a random frame: our bump
    normal in the nested diffuse equals Mitsuba's bumpmap eval."""
    rng = np.random.default_rng(5)
    heights = rng.random((4, 5))
    texture = bitmap("h", np.repeat(heights[:, :, None], 3, axis=2))
    bsdf = mi.load_dict({"type": "bumpmap", "scale": 0.3,
                         "tex": {"type": "bitmap", "raw": True,
                                 "data": mi.TensorXf(heights[:, :, None].astype(np.float32))},
                         "bsdf": {"type": "diffuse", "reflectance": {"type": "rgb", "value": 0.5}}})
    for _ in range(200):
        rot = _rotation(rng)
        wi, wo = _directions(rng, rot)
        uv = rng.random(2) * 0.5
        ns, a2, n = _ours(Material("m", bump_map=0, bump_scale=0.3), texture, rot, uv, wi)
        theirs = _mitsuba_value(mi, bsdf, rot, uv, wi, wo)
        assert _our_value(ns, a2, n, wi, wo) == pytest.approx(theirs, rel=2e-4, abs=1e-6)


PLANE = """<scene version="3.0.0">
  <sensor type="perspective"><float name="fov" value="20"/>
    <transform name="to_world"><lookat origin="0,0,5" target="0,0,0" up="0,1,0"/></transform>
    <film type="hdrfilm"><integer name="width" value="8"/><integer name="height" value="8"/></film>
  </sensor>
  <shape type="rectangle"><transform name="to_world"><scale value="4"/></transform>{bsdf}</shape>
  <emitter type="directional"><vector name="direction" value="{light}"/>
    <rgb name="irradiance" value="2"/></emitter>
</scene>
"""
DIFFUSE = '<bsdf type="diffuse"><rgb name="reflectance" value="0.6"/></bsdf>'
MAPPED = ('<bsdf type="normalmap"><texture name="normalmap" type="rawconstant">'
          '<vector name="value" value="{c}"/></texture>'
          '<boolean name="use_shadowing_function" value="{shadow}"/>' + DIFFUSE + '</bsdf>')


def _plane(tmp_path, bsdf, light=(0.0, -0.5, -1.0)):
    path = tmp_path / "plane.xml"
    path.write_text(PLANE.format(bsdf=bsdf, light=", ".join(map(str, light))))
    return load_mitsuba_xml(str(path))


def test_flat_normal_map_is_the_wrapped_bsdf(tmp_path):
    """A normal map of (0.5, 0.5, 1) everywhere changes nothing: the image
    equals the bare diffuse's bit for bit, photons included."""
    light = (0.3, -0.5, -1.0)
    bare = dp.render(_plane(tmp_path, DIFFUSE, light), iterations=4, mode="sppm", seed=1, max_depth=3)
    mapped = dp.render(_plane(tmp_path, MAPPED.format(c="0.5, 0.5, 1", shadow="true"), light),
                       iterations=4, mode="sppm", seed=1, max_depth=3)
    assert np.asarray(bare).mean() > 0
    np.testing.assert_array_equal(np.asarray(mapped), np.asarray(bare))


@pytest.mark.parametrize("shadow", [False, True])
def test_tilted_normal_map_closed_form(tmp_path, shadow):
    """A plane whose normal map tilts every normal by 30 degrees toward
    +y (the rectangle's dp/dv), lit by a directional light: each pixel is the flat
    plane's times cos(tilted normal, light) / cos(normal, light), and with
    the shadowing function times G(light) of Estevez et al."""
    tilt = math.radians(30)
    local = np.array([0.0, math.sin(tilt), math.cos(tilt)])
    c = ", ".join(f"{x:.9f}" for x in 0.5 * local + 0.5)
    light = np.array([0.0, -0.5, -1.0])
    to_light = -light / np.linalg.norm(light)
    flat = np.asarray(dp.render(_plane(tmp_path, DIFFUSE), iterations=2, mode="sppm", seed=1, max_depth=2))
    mapped = np.asarray(dp.render(_plane(tmp_path, MAPPED.format(c=c, shadow=str(shadow).lower())),
                                  iterations=2, mode="sppm", seed=1, max_depth=2))
    ratio = np.dot(local, to_light) / to_light[2]
    if shadow:
        a2 = min(0.125 * (1 - local[2] ** 2) / local[2] ** 2, 1.0)
        ratio *= 2 / (1 + math.sqrt(1 + a2 * (1 - to_light[2] ** 2) / to_light[2] ** 2))
    assert flat.min() > 0 and ratio > 1.05
    np.testing.assert_allclose(mapped, flat * ratio, rtol=1e-5)


BSDF_SPHERES = os.path.join(os.path.dirname(__file__), "..", "..", "shared", "scenes", "mitsuba-data",
                            "tests", "scenes", "bsdf_spheres")

# A normal-mapped floor under a narrow spot, and a wall the spot does not
# reach: all of the wall's light comes off the floor, by photons.
def _bounce(c: str, far=False) -> str:
    """The floor-and-wall scene, the floor diffuse under a normal map of
    the constant (raw) value `c`, the spot narrower and straight down."""
    return floor_and_wall(f"""<bsdf type="normalmap"><texture name="normalmap" type="rawconstant">
      <vector name="value" value="{c}"/></texture>
      <bsdf type="diffuse"><rgb name="reflectance" value="0.8"/></bsdf></bsdf>""", "1,0,0", 15, 10, far)


@pytest.mark.reference
@pytest.mark.slow
def test_light_off_a_normal_mapped_floor_matches_mitsuba(mi, tmp_path):
    """The wall is lit only by what a floor tilted 40 degrees by its normal
    map sends it: photons carry Veach's adjoint of the shading-normal BSDF
    (with the naive weight f |wo.ns| / p and unscaled deposits the wall
    came out 2.7 times too bright). The wall's mean within 4% of Mitsuba's
    path tracer, the whole image's too."""
    tilt = math.radians(40)
    c = ", ".join(f"{x:.9f}" for x in 0.5 + 0.5 * np.array([-math.sin(tilt), 0.0, math.cos(tilt)]))
    path = tmp_path / "bounce.xml"
    path.write_text(_bounce(c))
    ours = np.asarray(dp.render(load_mitsuba_xml(str(path)), iterations=300, mode="sppm", seed=2))
    ref = np.asarray(mi.render(mi.load_file(str(path)), spp=2048, seed=1))[..., :3]
    wall = np.zeros(ours.shape[:2], bool)
    wall[:12] = True                      # the top half of the image looks at the wall only
    assert ref[wall].mean() > 0.02 * ref.mean()
    assert ours[wall].mean() == pytest.approx(ref[wall].mean(), rel=0.04)
    assert ours.mean() == pytest.approx(ref.mean(), rel=0.04)


def test_chunked_equals_unchunked(tmp_path, chunk_store):
    """The floor-and-wall scene and, far off, a checkerboard (texture 0;
    the floor's normal map is texture 1, renumbered 0 in its chunk), cut by
    the real subdivider into 2 chunks and rendered by OSPPM from the
    store: the unchunked image up to float noise."""
    from dosppm_core.settings import RenderSettings
    path = tmp_path / "chunked.xml"
    path.write_text(_bounce("0.75, 0.5, 0.933", far=True))
    scene = load_mitsuba_xml(str(path))
    store = chunk_store(scene, chunks=2)
    assert store.chunk_count == 2 and len(store.header.textures) == 2
    _floor_chunk_renumbers_its_map(scene)
    ref, img = sppm_and_osppm_images(scene, store, RenderSettings(seed=11, photons_per_iteration=30_000), 3)
    assert ref.mean() > 0
    assert_equal_up_to_float_noise(img, ref)


def _floor_chunk_renumbers_its_map(scene):
    """A chunk holding only the floor carries only its normal map (texture
    1 of the scene), which its kernels then read as texture 0."""
    floor = int(np.flatnonzero(scene.materials.normal_map >= 0)[0])
    assert scene.materials.normal_map[floor] == 1
    chunk, mats, table = one_triangle_chunk(scene, floor)
    assert chunk.tex_ids.tolist() == [1]
    assert mats.normal_map[floor] == 0 and len(table) == 1 and (mats.texture == -1).all()


@pytest.mark.reference
def test_named_conductors_are_mitsubas(mi, tmp_path):
    """Every metal Mitsuba names (`material="Al"`) has its eta and k as
    Mitsuba's RGB variant computes them, and the reader gives them to
    conductors and rough conductors (naming eta too is an error)."""
    from dosppm_core.scene.mitsuba.metals import CONDUCTORS
    from dosppm_core.scene.model import SceneError
    for name, (eta, k) in CONDUCTORS.items():
        p = mi.traverse(mi.load_dict({"type": "conductor", "material": name}))
        np.testing.assert_allclose(eta, list(p["eta.value"]), rtol=1e-5)
        np.testing.assert_allclose(k, list(p["k.value"]), rtol=1e-5)
    assert len(CONDUCTORS) > 60
    metal = '<bsdf type="roughconductor"><string name="material" value="Au"/>{eta}</bsdf>'
    scene = _plane(tmp_path, metal.format(eta=""))
    np.testing.assert_array_equal(scene.materials.conductor_eta[0], np.float32(CONDUCTORS["Au"][0]))
    np.testing.assert_array_equal(scene.materials.conductor_k[0], np.float32(CONDUCTORS["Au"][1]))
    with pytest.raises(SceneError, match="not both"):
        _plane(tmp_path, metal.format(eta='<float name="eta" value="1"/>'))
