"""Textured delta lights (issue 33): Mitsuba's spot with a `texture` and
projector with an `irradiance` image (`scene.light_textures`).

Closed forms: a constant texture equals the untextured light of that
value (same power, same image from the same seed, photons and shadow rays
alike), and a projector's flux is pi x its image plane's area x the mean
texel. The image's orientation (which texel goes where) is checked against
Mitsuba 3 rendering the same file, for both lights.
"""
from __future__ import annotations

import math

import numpy as np
import pytest

import dosppm_core as dp
from dosppm_core.scene.model import LIGHT_PROJECTOR, LIGHT_SPOT, SceneError
from tests.helpers.renders import assert_chunks_render_the_scene, mitsuba_scene, quadrants

PLANE = """<shape type="rectangle"><transform name="to_world"><scale value="3"/><rotate y="1" angle="180"/>
    <translate z="1"/></transform>
    <bsdf type="diffuse"><rgb name="reflectance" value="0.8"/></bsdf></shape>"""


def _png(tmp_path, rgb, name="tex.png") -> str:
    """An 8-bit PNG of (H, W, 3) values in [0, 255]."""
    from PIL import Image
    path = tmp_path / name
    Image.fromarray(np.asarray(rgb, np.uint8)).save(path)
    return str(path)


def _scene(tmp_path, emitter: str, name="scene.xml", size=24) -> str:
    """The light at the origin looking along +z at a plane at z = 1 (facing
    it), the camera behind the light."""
    return mitsuba_scene(tmp_path, emitter, PLANE, size, origin="0, 0, -0.2", target="0, 0, 1", fov=90,
                         name=name)


LOOK = '<transform name="to_world"><lookat origin="0, 0, 0" target="0, 0, 1" up="0, 1, 0"/></transform>'


def _spot(intensity, texture="") -> str:
    return f"""<emitter type="spot"><rgb name="intensity" value="{intensity}"/>{texture}
        <float name="cutoff_angle" value="40"/><float name="beam_width" value="30"/>{LOOK}</emitter>"""


def _projector(irradiance="", texture="") -> str:
    return f"""<emitter type="projector"><float name="fov" value="70"/>{irradiance}{texture}{LOOK}</emitter>"""


def _bitmap(path, name, raw=True) -> str:
    return (f'<texture type="bitmap" name="{name}"><string name="filename" value="{path}"/>'
            f'<boolean name="raw" value="{"true" if raw else "false"}"/></texture>')


def _render(scene, direct, iterations=4):
    return np.asarray(dp.render(scene, iterations=iterations, mode="sppm", seed=5, direct=direct,
                                photons_per_iteration=20_000))


@pytest.mark.parametrize("direct", ["nee", "photons"])
def test_constant_textured_spot_equals_the_untextured_one(tmp_path, direct):
    """A grey image of value g on a spot of intensity I is the spot of
    intensity g I: its power (the texture's quadrature against the
    falloff's closed form) and its image, by photons or by shadow rays."""
    g = 128
    png = _png(tmp_path, np.full((3, 5, 3), g))
    textured = dp.load(_scene(tmp_path, _spot("2, 1, 3", _bitmap(png, "texture")), "a.xml"))
    plain = dp.load(_scene(tmp_path, _spot(f"{2 * g / 255}, {g / 255}, {3 * g / 255}"), "b.xml"))
    assert textured.lights.kind[0] == LIGHT_SPOT and textured.lights.texture[0] == 0
    assert plain.lights.texture[0] == -1
    np.testing.assert_allclose(textured.lights.power, plain.lights.power, rtol=2e-3)
    a, b = _render(textured, direct), _render(plain, direct)
    assert b.mean() > 0
    np.testing.assert_allclose(a, b, rtol=1e-4, atol=1e-7)


@pytest.mark.parametrize("direct", ["nee", "photons"])
def test_constant_textured_projector_equals_the_untextured_one(tmp_path, direct):
    g = 200
    png = _png(tmp_path, np.full((4, 4, 3), g))
    textured = dp.load(_scene(tmp_path, _projector(texture=_bitmap(png, "irradiance")), "a.xml"))
    plain = dp.load(_scene(tmp_path, _projector(f'<rgb name="irradiance" value="{g / 255}"/>'), "b.xml"))
    assert textured.lights.kind[0] == LIGHT_PROJECTOR and textured.lights.texture[0] == 0
    np.testing.assert_allclose(textured.lights.power, plain.lights.power, rtol=1e-6)
    a, b = _render(textured, direct), _render(plain, direct)
    assert b.mean() > 0
    np.testing.assert_allclose(a, b, rtol=1e-4, atol=1e-7)


def test_projector_flux_and_frustum_follow_the_image_aspect(tmp_path):
    """A 2:1 image: the frustum's half extents are tan(fov/2) across and
    half that up, and the power pi x 4 tan_x tan_y x the mean texel."""
    texels = np.zeros((2, 4, 3))
    texels[:, :2] = 255
    png = _png(tmp_path, texels)
    scene = dp.load(_scene(tmp_path, _projector('<float name="scale" value="3"/>', _bitmap(png, "irradiance"))))
    L = scene.lights
    tan_x = math.tan(math.radians(35))
    np.testing.assert_allclose(L.cone[0, :2], [tan_x, tan_x / 2])
    np.testing.assert_allclose(L.power[0], 3 * math.pi * 4 * tan_x * tan_x / 2 * 0.5, rtol=1e-3)


def test_texture_under_another_name_is_refused(tmp_path):
    png = _png(tmp_path, np.full((2, 2, 3), 9))
    with pytest.raises(SceneError) as err:
        dp.load(_scene(tmp_path, _spot("1", _bitmap(png, "intensity"))))
    assert "\n" not in str(err.value) and "takes one texture, named 'texture'" in str(err.value)


@pytest.mark.reference
@pytest.mark.parametrize("light", ["spot", "projector"])
def test_textured_light_matches_mitsuba(tmp_path, light, mi):
    """Four coloured quadrants (sRGB-decoded) thrown on the plane: each
    quadrant of our image within 4% of Mitsuba 3's render of the same
    file (`direct`, box filter), so the image is neither mirrored nor
    turned, and its brightness matches."""
    texels = quadrants()
    png = _png(tmp_path, texels)
    emitter = (_spot("4", _bitmap(png, "texture", raw=False)) if light == "spot" else
               _projector(texture=_bitmap(png, "irradiance", raw=False)))
    path = _scene(tmp_path, emitter, size=32)
    ours = _render(dp.load(path), "nee", iterations=32)
    scene = mi.load_file(path)
    theirs = np.array(mi.render(scene, spp=256, sensor=scene.sensors()[0],
                                integrator=mi.load_dict({"type": "direct"})))[:, :, :3]
    q_ours, q_theirs = (x[4:28, 4:28].reshape(2, 12, 2, 12, 3).mean(axis=(1, 3)) for x in (ours, theirs))
    assert q_theirs.sum(axis=2).min() > 0.1
    np.testing.assert_allclose(q_ours, q_theirs, rtol=0.03, atol=0.005)


def test_header_carries_the_light_textures_over_the_wire(tmp_path):
    """Tracers get the lights' textures with the header (every chunk needs them)."""
    import msgpack

    from dosppm_core.scene.model import SceneHeader
    png = _png(tmp_path, np.arange(24).reshape(2, 4, 3) * 10)
    scene = dp.load(_scene(tmp_path, _spot("1", _bitmap(png, "texture"))))
    header = SceneHeader.from_wire(msgpack.unpackb(msgpack.packb(scene.header().to_wire())))
    a, b = scene.lights, header.lights
    assert a.tex_texels.shape == (8, 3)
    for name, value in a.wire_fields().items():
        np.testing.assert_array_equal(getattr(b, name), value, err_msg=name)


# -- area lights with a textured radiance -------------------------------------------------
def _area_scene(tmp_path, radiance: str, name="area.xml", size=32) -> str:
    """A 1 x 1 emitting rectangle facing the camera (rows 9 to 19 of the
    view) above a diffuse floor it lights (the rows below)."""
    text = f"""<scene version="3.0.0">
    <sensor type="perspective"><float name="fov" value="60"/>
        <transform name="to_world"><lookat origin="0, 1.5, 3" target="0, 0.6, 0" up="0, 1, 0"/></transform>
        <sampler type="independent"><integer name="sample_count" value="64"/></sampler>
        <film type="hdrfilm"><integer name="width" value="{size}"/><integer name="height" value="{size}"/>
            <rfilter type="box"/></film>
    </sensor>
    <shape type="rectangle"><transform name="to_world"><scale value="0.5"/><translate y="0.8"/></transform>
        <emitter type="area">{radiance}</emitter></shape>
    <shape type="rectangle"><transform name="to_world"><scale value="3"/><rotate x="1" angle="-90"/>
        <translate y="0.2"/></transform><bsdf type="diffuse"><rgb name="reflectance" value="0.8"/></bsdf></shape>
</scene>"""
    path = tmp_path / name
    path.write_text(text)
    return str(path)


@pytest.mark.parametrize("direct", ["nee", "photons"])
def test_constant_textured_area_light_equals_the_untextured_one(tmp_path, direct):
    """A grey image of value g as an area light's radiance is the radiance
    g: the same power, and the same image (the light seen and the floor it
    lights) from the same seed."""
    g = 150
    png = _png(tmp_path, np.full((4, 6, 3), g))
    textured = dp.load(_area_scene(tmp_path, _bitmap(png, "radiance"), "a.xml"))
    plain = dp.load(_area_scene(tmp_path, f'<rgb name="radiance" value="{g / 255}"/>', "b.xml"))
    assert (textured.lights.texture >= 0).sum() == 2 and (plain.lights.texture >= 0).sum() == 0
    np.testing.assert_allclose(textured.lights.power, plain.lights.power, rtol=1e-6)
    a, b = _render(textured, direct), _render(plain, direct)
    assert b[10:18, 12:20].mean() > 0.5 and b[-8:].mean() > 0
    np.testing.assert_allclose(a, b, rtol=1e-4, atol=1e-7)


@pytest.mark.reference
@pytest.mark.parametrize("direct", ["nee", "photons"])
def test_textured_area_light_matches_mitsuba(tmp_path, direct, mi):
    """Four coloured quadrants as the radiance: the light seen (each
    quadrant where Mitsuba 3 shows it) and the floor it lights within 4%
    of Mitsuba's render of the same file, whether shadow rays or photons
    carry the floor's light."""
    texels = quadrants()
    path = _area_scene(tmp_path, _bitmap(_png(tmp_path, texels), "radiance", raw=False))
    ours = _render(dp.load(path), direct, iterations=32)
    scene = mi.load_file(path)
    theirs = np.array(mi.render(scene, spp=256, sensor=scene.sensors()[0],
                                integrator=mi.load_dict({"type": "direct"})))[:, :, :3]
    light_ours, light_theirs = (x[8:20, 10:22].reshape(2, 6, 2, 6, 3).mean(axis=(1, 3)) for x in (ours, theirs))
    assert light_theirs.sum(axis=2).min() > 0.5
    np.testing.assert_allclose(light_ours, light_theirs, rtol=0.03, atol=0.005)
    floor_ours, floor_theirs = (x[-10:].reshape(10, 2, 16, 3).mean(axis=(0, 2)) for x in (ours, theirs))
    np.testing.assert_allclose(floor_ours, floor_theirs, rtol=0.04)


def test_chunked_textured_area_light_render_equals_unchunked(tmp_path):
    """OSPPM over 8 chunks renders the textured lamp and floor as SPPM
    does: the chunks read the light table's textures (eye rays seeing the
    lamp, BSDF-sampled rays finding it, photons and shadow rays)."""
    texels = np.zeros((8, 8, 3))
    texels[:4] = (255, 40, 40)
    texels[4:] = (40, 40, 255)
    path = _area_scene(tmp_path, _bitmap(_png(tmp_path, texels), "radiance"), size=24)
    assert_chunks_render_the_scene(dp.load(path), (2, 2, 2))


@pytest.mark.parametrize("filter_type", ["bilinear", "nearest"])
@pytest.mark.parametrize("wrap_mode", ["repeat", "mirror", "clamp"])
def test_flux_lookup_equals_the_kernels(filter_type, wrap_mode):
    """The scene layer's numpy lookup (for the lights' flux) reads the
    texels the kernels read, inside and outside [0, 1]^2, under a to_uv."""
    from dosppm_core.kernels.texture import lookup_many
    from dosppm_core.scene.light_textures import lookup
    from dosppm_core.scene.textures import TextureTable, bitmap, checkerboard
    rng = np.random.default_rng(4)
    s, r = rng.uniform(-1.5, 2.5, 2000), rng.uniform(-1.5, 2.5, 2000)
    for texture in (bitmap("b", rng.uniform(0, 1, (5, 7, 3)), filter_type, wrap_mode, (1.5, 0.2, 0.1, -0.3, 2, 0.4)),
                    checkerboard("c", (0.1, 0.2, 0.3), (0.9, 0.8, 0.7), (3, 0, 0, 0, 3, 0))):
        table = TextureTable.from_textures([texture])
        np.testing.assert_allclose(lookup(texture, s, r),
                                   lookup_many(table.info, table.uv_map, table.texels, 0, s, r), rtol=1e-6)
