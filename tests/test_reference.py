"""Mitsuba 3 as the reference renderer: the scene translation must give
closed-form radiance, the right orientation and the right one-sidedness."""
import math
import sys

import numpy as np
import pytest

from dosppm_core.film import read_exr
from dosppm_core.scene import loaders
from dosppm_core.scene.model import Camera, Material, SceneBuilder, SceneError
from harness import mitsuba_probe, reference
from harness.mitsuba_probe import best_variant
from services.cli.main import main as dosppm_main

pytestmark = pytest.mark.reference   # skipped without Mitsuba (tests/conftest.py)

# Tests force scalar_rgb: it always works and needs no kernel compilation.
VARIANT = "scalar_rgb"
RHO = 0.6
INTENSITY = 5.0
LIGHT = np.array([0.7, 0.4, 1.0])


def _camera(width=15, height=11, **kw):
    args = dict(position=(0, 0, 3), look_at=(0, 0, 0), up=(0, 1, 0), fov_deg=40.0,
                width=width, height=height)
    args.update(kw)
    return Camera(**args)


def _quad(size=10.0, z=0.0, flip=False):
    """A square in the plane z, CCW (front +z) unless `flip`."""
    s = size / 2
    v = [(-s, -s, z), (s, -s, z), (s, s, z), (-s, s, z)]
    f = [(0, 2, 1), (0, 3, 2)] if flip else [(0, 1, 2), (0, 2, 3)]
    return v, f


def _lit_plane_scene(flip=False, two_sided=True, light=LIGHT, camera=None):
    b = SceneBuilder(name="lit plane")
    b.add_material(Material("floor", reflectance=(RHO, RHO, RHO), two_sided=two_sided))
    b.add_mesh(*_quad(flip=flip), "floor", "test")
    b.add_point_light(light, (INTENSITY,) * 3, "test light")
    b.camera = camera or _camera()
    return b.build()


def _closed_form_plane(scene, light=LIGHT, sub=8):
    """Radiance of a Lambertian plane z=0 under a point light,
    L = rho / pi * I * cos(theta) / d^2, averaged over a sub x sub grid in
    each pixel as the box filter does."""
    pos, right, up, fwd, (tx, ty, _), _ = scene.camera.frame()[:6]
    w, h = scene.camera.width, scene.camera.height
    x = (2 * (np.arange(w * sub) + 0.5) / (w * sub) - 1) * tx
    y = (1 - 2 * (np.arange(h * sub) + 0.5) / (h * sub)) * ty     # row 0 is the top
    d = fwd + x[None, :, None] * right + y[:, None, None] * up
    p = pos + d * (-pos[2] / d[..., 2:3])
    to_light = light - p
    dist2 = np.sum(to_light ** 2, axis=-1)
    radiance = RHO / math.pi * INTENSITY * np.abs(to_light[..., 2]) / dist2 ** 1.5
    return radiance.reshape(h, sub, w, sub).mean(axis=(1, 3))


def test_point_lit_plane_matches_closed_form_per_pixel():
    scene = _lit_plane_scene()
    img = reference.render_reference(scene, spp=1024, max_depth=1, variant=VARIANT)
    assert img.shape == (11, 15, 3) and img.dtype == np.float32
    expected = _closed_form_plane(scene)
    # Only pixel jitter is random (the point light is sampled exactly).
    np.testing.assert_allclose(img[..., 1], expected, rtol=0.01)
    # Orientation: the light is up and to the right, so is the bright corner.
    assert img[0, -1, 0] > img[-1, 0, 0]


def test_plane_back_side_is_black_unless_two_sided():
    light_below = np.array([0.2, 0.1, -1.0])
    cam = _camera()
    back = _lit_plane_scene(flip=True, two_sided=False, light=light_below, camera=cam)
    img = reference.render_reference(back, spp=4, max_depth=1, variant=VARIANT)
    assert img.max() == 0.0
    lit = _lit_plane_scene(flip=True, two_sided=False, light=LIGHT, camera=cam)
    img = reference.render_reference(lit, spp=4, max_depth=1, variant=VARIANT)
    assert img.max() == 0.0   # light in front, but the front faces -z now
    both = _lit_plane_scene(flip=True, two_sided=True, camera=cam)
    img = reference.render_reference(both, spp=1024, max_depth=1, variant=VARIANT)
    np.testing.assert_allclose(img[..., 0], _closed_form_plane(both), rtol=0.01)


def _emitter_scene(flip):
    b = SceneBuilder(name="emitter")
    b.add_material(Material("lamp", reflectance=(0, 0, 0), emission=(2.0, 3.0, 4.0)))
    b.add_mesh(*_quad(size=10.0, flip=flip), "lamp", "test")
    b.camera = _camera(width=4, height=3)
    return b.build()


def test_area_light_is_one_sided_and_seen_at_depth_zero():
    img = reference.render_reference(_emitter_scene(False), spp=1, max_depth=0, variant=VARIANT)
    np.testing.assert_allclose(img, np.broadcast_to([2.0, 3.0, 4.0], img.shape), rtol=1e-5)
    img = reference.render_reference(_emitter_scene(True), spp=1, max_depth=0, variant=VARIANT)
    assert img.max() == 0.0


def test_spot_light_full_intensity_inside_beam_and_dark_outside():
    b = SceneBuilder(name="spot")
    b.add_material(Material("floor", reflectance=(RHO,) * 3))
    b.add_mesh(*_quad(), "floor", "test")
    b.add_spot_light((0, 0, 1), (0, 0, 0), (INTENSITY,) * 3, 20.0, 10.0, "spot")
    # Small pixels: the centre one sees cos^3 within 0.3% of 1.
    b.camera = _camera(width=61, height=61, fov_deg=90.0)
    img = reference.render_reference(b.build(), spp=4, max_depth=1, variant=VARIANT)
    np.testing.assert_allclose(img[30, 30], RHO / math.pi * INTENSITY, rtol=0.01)
    assert img[0, 0].max() == 0.0   # at 90 degrees fov the corner is far outside


def test_depth_mapping_and_dict_translation():
    assert reference.mitsuba_max_depth(0) == 1
    assert reference.mitsuba_max_depth(10) == 11
    assert reference.mitsuba_max_depth(-1) == -1
    b = SceneBuilder(name="mix")
    mats = [Material("d", two_sided=False), Material("m", kind="mirror"),
            Material("g", kind="glass", ior=1.33, reflectance=(1.0, 1.2, 1.0)),
            Material("r", kind="glossy", roughness=0.3)]
    for k, mat in enumerate(mats):
        b.add_material(mat)
        b.add_mesh(*_quad(size=1.0, z=-k), mat.name, "test")
    b.add_point_light((0, 0, 2), (1, 1, 1), "p")
    b.camera = _camera(aperture_radius=0.1, focus_distance=3.0)
    d = reference.scene_to_mitsuba_dict(b.build(), spp=3, max_depth=4, integrator="ptracer",
                                        seed=7, variant=VARIANT)
    assert d["integrator"] == {"type": "ptracer", "max_depth": 5, "hide_emitters": False}
    assert d["sensor"]["type"] == "thinlens" and d["sensor"]["film"]["rfilter"] == {"type": "box"}
    assert d["sensor"]["sampler"] == {"type": "independent", "sample_count": 3, "seed": 7}
    assert sorted(k for k in d if k.startswith("mesh_")) == ["mesh_0_d", "mesh_1_m", "mesh_2_g", "mesh_3_r"]
    assert "light_0" in d
    bsdfs = {k: str(d[k].bsdf()) for k in d if k.startswith("mesh_")}
    assert bsdfs["mesh_0_d"].startswith("SmoothDiffuse")          # not two-sided
    assert bsdfs["mesh_1_m"].startswith("TwoSided") and "SmoothConductor" in bsdfs["mesh_1_m"]
    assert bsdfs["mesh_2_g"].startswith("SmoothDielectric")       # glass is never wrapped
    assert "RoughConductor" in bsdfs["mesh_3_r"] and "0.3" in bsdfs["mesh_3_r"]


def test_bad_integrator_and_spp_rejected():
    scene = _lit_plane_scene()
    with pytest.raises(ValueError, match="integrator"):
        reference.scene_to_mitsuba_dict(scene, 4, 1, integrator="bdpt", variant=VARIANT)
    with pytest.raises(ValueError, match="spp"):
        reference.scene_to_mitsuba_dict(scene, 0, 1, variant=VARIANT)


def test_cached_reference_renders_once(tmp_path, monkeypatch):
    scene = _lit_plane_scene(camera=_camera(width=5, height=4))
    first = reference.cached_reference(scene, 2, str(tmp_path), max_depth=1, variant=VARIANT)
    assert len(list(tmp_path.glob("ref-*.exr"))) == 1

    def no_render(*a, **k):
        raise AssertionError("rendered again despite the cache")
    monkeypatch.setattr(reference, "render_reference", no_render)
    again = reference.cached_reference(scene, 2, str(tmp_path), max_depth=1, variant=VARIANT)
    np.testing.assert_array_equal(first, again)
    key = reference.reference_key
    assert key(scene, 2, 1) != key(scene, 3, 1) != key(scene, 2, 2)
    assert key(scene, 2, 1) != key(scene, 2, 1, integrator="ptracer")


def test_missing_mitsuba_gives_install_hint(monkeypatch):
    monkeypatch.setitem(sys.modules, "mitsuba", None)   # makes `import mitsuba` fail
    with pytest.raises(reference.ReferenceRenderError, match=r"pip install 'dosppm\[reference\]'"):
        reference.render_reference(_lit_plane_scene(), 1, variant=VARIANT)


def test_best_variant_is_a_working_variant():
    """The probe (a child process, outside the library) answers a variant
    that renders here."""
    variant = best_variant()
    assert variant in (reference.FAST_VARIANT, reference.SAFE_VARIANT)
    assert reference.render_reference(_emitter_scene(False), 1, max_depth=0, variant=variant).shape == (3, 4, 3)


# -- dosppm reference ---------------------------------------------------------
def _run_reference(argv):
    return dosppm_main(["reference", *argv])


def test_reference_command_writes_exr(tmp_path, monkeypatch, capsys):
    seen = {}

    def fake_load(spec, **overrides):
        seen.update(overrides, spec=spec)
        scene = _emitter_scene(False)
        scene.camera.width, scene.camera.height = overrides["width"], overrides["height"]
        return scene
    monkeypatch.setattr(loaders, "load_scene", fake_load)
    out = str(tmp_path / "ref.exr")
    code = _run_reference(["lamp.toml", "--spp", "2", "--out", out, "--max-depth", "0",
                           "--width", "6", "--height", "4", "--variant", VARIANT])
    assert code == 0
    assert seen == {"spec": "lamp.toml", "width": 6, "height": 4}
    rgb, _ = read_exr(out)
    np.testing.assert_allclose(rgb, np.broadcast_to([2.0, 3.0, 4.0], (4, 6, 3)), rtol=1e-5)
    assert "wrote" in capsys.readouterr().out


def test_reference_command_without_variant_asks_the_probe(tmp_path, monkeypatch, capsys):
    """No --variant: the command takes the probe's answer (harness/mitsuba_probe.py)."""
    asked = []
    monkeypatch.setattr(mitsuba_probe, "best_variant", lambda: asked.append(1) or VARIANT)
    monkeypatch.setattr(loaders, "load_scene", lambda spec, **overrides: _emitter_scene(False))
    out = str(tmp_path / "ref.exr")
    assert _run_reference(["lamp.toml", "--spp", "1", "--out", out, "--max-depth", "0"]) == 0
    assert asked == [1] and f"{VARIANT}," in capsys.readouterr().out
    assert read_exr(out)[0].shape == (3, 4, 3)


def test_reference_command_bad_scene_exits_2(tmp_path, monkeypatch, capsys):

    def broken(spec, **overrides):
        raise SceneError(f"{spec}: no such file, and not a built-in scene")
    monkeypatch.setattr(loaders, "load_scene", broken)
    code = _run_reference(["nope.toml", "--spp", "1", "--out", str(tmp_path / "x.exr")])
    err = capsys.readouterr().err
    assert code == 2 and "nope.toml" in err and err.count("\n") == 1
    assert not (tmp_path / "x.exr").exists()


SMOOTH_SPHERE = """<scene version="3.0.0">
  <integrator type="path"/>
  <sensor type="perspective"><float name="fov" value="35"/>
    <transform name="to_world"><lookat origin="0,-5,1.5" target="0,0,0" up="0,0,1"/></transform>
    <film type="hdrfilm"><integer name="width" value="32"/><integer name="height" value="32"/>
      <rfilter type="box"/></film>
  </sensor>
  <shape type="obj"><string name="filename" value="{meshes}/sphere.obj"/>{flat}
    <bsdf type="conductor"/></shape>
  <shape type="rectangle"><transform name="to_world"><scale value="4"/><translate z="-1"/></transform>
    <bsdf type="diffuse"><rgb name="reflectance" value="0.3, 0.5, 0.7"/></bsdf></shape>
  <shape type="rectangle"><transform name="to_world"><scale value="1.5"/><rotate x="1" angle="180"/>
    <translate x="0.5" z="3"/></transform><emitter type="area"><rgb name="radiance" value="5"/></emitter></shape>
</scene>
"""


def test_a_smooth_mesh_reaches_mitsuba_with_its_vertex_normals(tmp_path):
    """A mesh read with vertex normals (smooth, as Mitsuba reads it) is
    handed to Mitsuba with them: the translated scene renders as Mitsuba
    renders the XML itself, and unlike the same mesh with face_normals
    (a faceted mirror sphere), which it used to match."""
    import mitsuba as mi

    from tests.helpers.paths import SHARED_SCENES
    meshes = f"{SHARED_SCENES}/mitsuba-data/common/meshes"
    images = {}
    for flat in (False, True):
        path = tmp_path / f"sphere-{flat}.xml"
        path.write_text(SMOOTH_SPHERE.format(
            meshes=meshes, flat='<boolean name="face_normals" value="true"/>' if flat else ""))
        scene = loaders.load_scene(str(path))
        assert bool(np.any(scene.normals)) != flat
        images[flat] = reference.render_reference(scene, 1024, variant=VARIANT)
        if not flat:
            mi.set_variant(VARIANT)
            own = mi.render(mi.load_file(str(path)), spp=1024, seed=3)
            images["mitsuba"] = np.asarray(own, np.float32)[..., :3]
    # 4x4 pixel blocks: noise falls by 4, the facets' reflections stay.
    blocks = {k: v.reshape(8, 4, 8, 4, 3).mean(axis=(1, 3)) for k, v in images.items()}
    scale = float(np.mean(blocks["mitsuba"]))
    same = float(np.mean(np.abs(blocks[False] - blocks["mitsuba"]))) / scale
    faceted = float(np.mean(np.abs(blocks[True] - blocks["mitsuba"]))) / scale
    assert same < 0.5 * faceted, (same, faceted)
