"""The coloured materials and masks in scenes: the Mitsuba reader's
mapping, the scene header's wire form, and renders against Mitsuba 3's
path tracer (rough plastic, smooth plastic, rough dielectric, a mask)."""
import os
import re

import numpy as np
import pytest

import dosppm_core as dp
from dosppm_core.scene.mitsuba import load_mitsuba_xml
from dosppm_core.scene.model import MATERIAL_KINDS, SceneError, SceneHeader

MITSUBA_TESTS = os.path.join(os.path.dirname(__file__), "..", "..", "shared", "scenes", "mitsuba-data",
                             "tests", "scenes", "bsdf_spheres")

SCENE = """<scene version="3.0.0">
  <sensor type="perspective"><float name="fov" value="35"/>
    <transform name="to_world"><lookat origin="0,1,5" target="0,0,0" up="0,1,0"/></transform>
    <film type="hdrfilm"><integer name="width" value="32"/><integer name="height" value="32"/></film>
  </sensor>
  <shape type="sphere"><float name="radius" value="1"/>{bsdf}</shape>
  <shape type="rectangle">
    <transform name="to_world"><rotate x="1" angle="90"/><translate y="4"/></transform>
    <emitter type="area"><rgb name="radiance" value="8"/></emitter></shape>
  <emitter type="point"><point name="position" x="3" y="2" z="3"/><rgb name="intensity" value="6"/></emitter>
  {extra}
</scene>
"""

BSDFS = {
    "roughplastic": '<bsdf type="roughplastic"><string name="distribution" value="ggx"/>'
                    '<float name="alpha" value="0.2"/><rgb name="diffuse_reflectance" value="0.2, 0.5, 0.3"/></bsdf>',
    "plastic": '<bsdf type="plastic"><rgb name="diffuse_reflectance" value="0.2, 0.5, 0.3"/>'
               '<boolean name="nonlinear" value="true"/></bsdf>',
    "roughdielectric": '<bsdf type="roughdielectric"><float name="alpha" value="0.5"/></bsdf>',
    "roughconductor": '<bsdf type="roughconductor"><float name="alpha" value="0.1"/>'
                      '<spectrum name="eta" value="0.789"/><spectrum name="k" value="6.15"/></bsdf>',
    "conductor": '<bsdf type="conductor"><rgb name="eta" value="0.2, 0.9, 1.1"/>'
                 '<rgb name="k" value="3.9, 2.4, 2.2"/></bsdf>',
}


def _write(tmp_path, text, name="scene.xml"):
    path = tmp_path / name
    path.write_text(text)
    return str(path)


def test_reader_maps_the_new_bsdfs(tmp_path):
    """Mitsuba's parameters and defaults: plastic's IOR polypropylene over
    air, roughdielectric's Beckmann and bk7, twosided, mask's opacity."""
    extra = """<shape type="rectangle"><bsdf type="mask"><float name="opacity" value="0.25"/>
        <bsdf type="twosided"><bsdf type="roughplastic"><float name="alpha" value="0.3"/>
        <rgb name="specular_reflectance" value="0.5"/></bsdf></bsdf></bsdf></shape>
      <shape type="disk"><bsdf type="twosided"><bsdf type="plastic"/></bsdf></shape>"""
    scene = load_mitsuba_xml(_write(tmp_path, SCENE.format(bsdf=BSDFS["roughdielectric"], extra=extra)))
    m = scene.materials
    by_kind = {int(k): i for i, k in enumerate(m.kind)}
    rd = by_kind[MATERIAL_KINDS["roughdielectric"]]
    assert m.ior[rd] == pytest.approx(1.5046 / 1.000277) and m.distribution[rd] == 1 and m.two_sided[rd]
    rp = by_kind[MATERIAL_KINDS["roughplastic"]]
    assert m.opacity[rp] == 0.25 and m.two_sided[rp] and m.roughness[rp] == pytest.approx(0.3)
    assert m.distribution[rp] == 1 and np.allclose(m.specular[rp], 0.5)      # Beckmann by default
    assert np.allclose(m.reflectance[rp], 0.5) and m.ior[rp] == pytest.approx(1.49 / 1.000277)
    p = by_kind[MATERIAL_KINDS["plastic"]]
    assert m.two_sided[p] and m.opacity[p] == 1.0
    scene = load_mitsuba_xml(_write(tmp_path, SCENE.format(bsdf=BSDFS["roughconductor"], extra="")))
    m = scene.materials
    rc = list(m.kind).index(MATERIAL_KINDS["roughconductor"])
    assert m.distribution[rc] == 1 and np.allclose(m.conductor_eta[rc], 0.789)    # Beckmann by default
    assert np.allclose(m.conductor_k[rc], 6.15) and not m.two_sided[rc]


def test_scene_header_wire_carries_the_new_columns(tmp_path):
    import msgpack
    scene = load_mitsuba_xml(_write(tmp_path, SCENE.format(bsdf=BSDFS["plastic"], extra="")))
    wire = msgpack.unpackb(msgpack.packb(scene.header().to_wire()))
    back = SceneHeader.from_wire(wire).materials
    for col in ("kind", "reflectance", "specular", "distribution", "nonlinear", "opacity", "ior",
                "conductor_eta", "conductor_k"):
        assert np.array_equal(getattr(back, col), getattr(scene.materials, col)), col


def test_principled_is_refused_in_one_line(tmp_path):
    path = _write(tmp_path, SCENE.format(bsdf='<bsdf type="principledthin"/>', extra=""))
    with pytest.raises(SceneError, match=r'scene\.xml:6: <bsdf type="principledthin">: the thin principled '
                                         r"BSDF is unsupported \(out of scope\)"):
        load_mitsuba_xml(path)


@pytest.mark.parametrize("name", ["test_roughdielectric_path", "test_roughplastic_linear_path",
                                  "test_roughplastic_nonlinear_path"])
def test_mitsuba_test_scenes_get_past_their_bsdfs(tmp_path, name):
    """Mitsuba's own bsdf_spheres scenes read to the end once their
    environment map (another part of issue 33) is left out."""
    path = os.path.join(MITSUBA_TESTS, f"{name}.xml")
    if not os.path.exists(path):
        pytest.skip("needs ../shared/scenes/mitsuba-data")
    common = os.path.abspath(os.path.join(MITSUBA_TESTS, "..", "..", "..", "common"))
    frag = open(os.path.join(MITSUBA_TESTS, "fragments", "single_sphere.xml")).read()
    frag = re.sub(r"<emitter type=\"envmap\">.*?</emitter>", "", frag, flags=re.S)
    _write(tmp_path, frag, "single_sphere.xml")
    text = open(path).read().replace('value="../../../common"', f'value="{common}"')
    text = text.replace("fragments/single_sphere.xml", "single_sphere.xml")
    scene = load_mitsuba_xml(_write(tmp_path, text))
    kinds = set(int(k) for k in scene.materials.kind)
    want = "roughdielectric" if "dielectric" in name else "roughplastic"
    assert MATERIAL_KINDS[want] in kinds


# -- renders against Mitsuba ------------------------------------------------------------
MASK_SCENE = """<scene version="3.0.0">
  <sensor type="perspective"><float name="fov" value="45"/>
    <transform name="to_world"><lookat origin="0,3,3" target="0,0,0" up="0,1,0"/></transform>
    <film type="hdrfilm"><integer name="width" value="32"/><integer name="height" value="32"/></film>
  </sensor>
  <shape type="rectangle"><transform name="to_world"><rotate x="1" angle="-90"/><scale value="3"/></transform>
    <bsdf type="diffuse"><rgb name="reflectance" value="0.6"/></bsdf></shape>
  <shape type="rectangle"><transform name="to_world"><rotate x="1" angle="-90"/><translate y="0.8"/></transform>
    <bsdf type="mask"><float name="opacity" value="0.4"/>
      <bsdf type="twosided"><bsdf type="diffuse"><rgb name="reflectance" value="0.8, 0.3, 0.2"/></bsdf></bsdf>
    </bsdf></shape>
  <shape type="rectangle"><transform name="to_world"><rotate x="1" angle="90"/><translate y="3"/></transform>
    <emitter type="area"><rgb name="radiance" value="6"/></emitter></shape>
</scene>
"""


def _render_pair(mi, path, iterations, spp):
    from harness.reference import render_reference
    scene = load_mitsuba_xml(path)
    ours = np.asarray(dp.render(scene, iterations=iterations, mode="sppm", seed=3))
    return ours, render_reference(scene, spp=spp)


@pytest.mark.reference
@pytest.mark.parametrize("bsdf", list(BSDFS))
def test_sphere_renders_as_mitsuba(mi, tmp_path, bsdf):
    """A sphere of each kind under an area and a point light: the image
    mean within 4% of Mitsuba's path tracer, and its blocks of 4x4 pixels
    brighter than the mean block within 10% of Mitsuba's (median). The rough
    dielectric is the noisiest (its hit points gather what the sphere
    transmits, the point light's caustics inside it): a broad alpha of 0.5,
    and 6% (three seeds of ours spread +-4% about Mitsuba's 16k spp)."""
    ours, ref = _render_pair(mi, _write(tmp_path, SCENE.format(bsdf=BSDFS[bsdf], extra="")), 600, 4096)
    assert ours.mean() == pytest.approx(ref.mean(), rel=0.06 if bsdf == "roughdielectric" else 0.04)
    blocks = lambda a: a.mean(2).reshape(8, 4, 8, 4).mean((1, 3))     # noqa: E731
    b_ours, b_ref = blocks(ours), blocks(ref)
    bright = b_ref > b_ref.mean()
    assert bright.sum() >= 4
    assert np.median(np.abs(b_ours[bright] / b_ref[bright] - 1)) < 0.1


@pytest.mark.reference
def test_mask_renders_as_mitsuba(mi, tmp_path):
    """A 40%-opaque red quad between a light and a grey floor: the floor
    seen through it and lit through it (by photons: shadow rays stop at a
    mask, a pass-through counts as a bounce) within 3% of Mitsuba."""
    ours, ref = _render_pair(mi, _write(tmp_path, MASK_SCENE), 400, 512)
    np.testing.assert_allclose(ours.mean((0, 1)), ref.mean((0, 1)), rtol=0.03)


def test_hash_gather_agrees_with_grid(tmp_path):
    """Both gathers weigh photons by the coloured BSDFs alike, a rough
    dielectric's photons from behind included: the image means agree
    within 2% (the hash keeps one photon per slot, so not exactly), where
    photons bring over 10% of the light."""
    scene = load_mitsuba_xml(_write(tmp_path, SCENE.format(bsdf=BSDFS["roughdielectric"], extra="")))
    grid = np.asarray(dp.render(scene, iterations=100, mode="sppm", seed=2, gather="grid"))
    hashed = np.asarray(dp.render(scene, iterations=100, mode="sppm", seed=2, gather="hash"))
    np.testing.assert_allclose(hashed.mean((0, 1)), grid.mean((0, 1)), rtol=0.02)
    direct = np.asarray(dp.render(scene, iterations=100, mode="sppm", seed=2, max_depth=1))
    assert grid.mean() > 1.1 * direct.mean()      # the photons matter here: not a test of NEE alone
