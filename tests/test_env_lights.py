"""Infinitely distant lights: Mitsuba's `directional`, `constant` and
`envmap` (issue 33, part 4).

Closed forms: a diffuse convex sphere under a uniform environment L has
radiance albedo x L (a white furnace), a diffuse plane under a directional
light E at angle theta has albedo E cos(theta) / pi, and the photons of
either kind cross a plane with the irradiance those give. The map's
sampler is checked by chi-square against its own pdf, its lookup against
Mitsuba's envmap, and a sphere and a floor under museum.exr against a
Mitsuba render. Chunked renders equal the unchunked one, and the header
carries the map over the wire.
"""
from __future__ import annotations

import math
import os

import msgpack
import numpy as np
import pytest

import dosppm_core as dp
from dosppm_core.kernels.envmap import env_arrays, env_eval, env_pdf, env_sample
from dosppm_core.modes.sppm import Renderer
from dosppm_core.scene.envmap import distribution, texels_from_image
from dosppm_core.scene.model import LIGHT_DIRECTIONAL, LIGHT_ENV, SceneError, SceneHeader
from dosppm_core.settings import RenderSettings
from dosppm_core.trace import emit_photon_job, emit_photon_jobs, environment, trace_photon_jobs
from tests.helpers.chunks import root_box, uniform_tree
from tests.helpers.paths import SHARED_SCENES, needs_shared_scenes
from tests.helpers.renders import assert_chunks_render_the_scene, mitsuba_scene

MITSUBA_DATA = os.path.join(SHARED_SCENES, "mitsuba-data")
MUSEUM = os.path.join(MITSUBA_DATA, "common", "textures", "museum.exr")
needs_museum = pytest.mark.skipif(not os.path.isfile(MUSEUM), reason="museum.exr (../shared) absent")


def _sphere(albedo, centre="0, 0, 0", radius=0.8):
    return f"""<shape type="sphere"><point name="center" value="{centre}"/><float name="radius" value="{radius}"/>
        <bsdf type="diffuse"><rgb name="reflectance" value="{albedo}"/></bsdf></shape>"""


def _render(scene, iterations, **kw):
    settings = dict(seed=3, photons_per_iteration=50_000)
    settings.update(kw)
    return np.asarray(dp.render(scene, iterations=iterations, mode="sppm", **settings))


def _disc_mask(size, frac):
    """Pixels within `frac` of the image's half width from its centre."""
    y, x = np.mgrid[:size, :size] + 0.5 - size / 2
    return np.hypot(x, y) < frac * size / 2


# -- closed forms ------------------------------------------------------------------------
@pytest.mark.parametrize("direct", ["nee", "photons"])
def test_white_furnace_sphere_under_a_constant_environment(tmp_path, direct):
    """A convex diffuse sphere sees the whole environment above each point
    and never itself: radiance albedo x L, the background L. Shadow rays
    carry it with `nee`; with `photons` every photon from the disc
    deposits, so their density must be right."""
    albedo, radiance = np.array([0.8, 0.5, 0.25]), np.array([1.0, 2.0, 0.5])
    path = mitsuba_scene(tmp_path,
                         '<emitter type="constant"><rgb name="radiance" value="1, 2, 0.5"/></emitter>',
                _sphere("0.8, 0.5, 0.25"), size=32, origin="0, 0, 6", fov=30)
    # nee: one shadow ray a pixel an iteration, few photons (they carry nothing here)
    img = _render(dp.load(path), 64, direct=direct, photons_per_iteration=10_000) if direct == "nee" else \
        _render(dp.load(path), 16, direct=direct)
    sphere = _disc_mask(32, 0.4)            # the sphere spans half the half width
    background = ~_disc_mask(32, 0.6)
    np.testing.assert_allclose(img[background].mean(0), radiance, rtol=1e-5)
    np.testing.assert_allclose(img[sphere].mean(0), albedo * radiance, rtol=0.03)


@pytest.mark.parametrize("direct", ["nee", "photons"])
def test_directional_light_on_a_diffuse_plane(tmp_path, direct):
    """A plane of albedo a under irradiance E arriving at 60 degrees from
    its normal: radiance a E cos(60) / pi everywhere on it."""
    s = math.sin(math.radians(60))
    emitter = f"""<emitter type="directional"><vector name="direction" value="{s}, -0.5, 0"/>
        <rgb name="irradiance" value="3, 2, 1"/></emitter>"""
    plane = """<shape type="rectangle"><transform name="to_world"><scale value="2"/><rotate x="1" angle="-90"/>
        </transform><bsdf type="diffuse"><rgb name="reflectance" value="0.6"/></bsdf></shape>"""
    scene = dp.load(mitsuba_scene(tmp_path, emitter, plane, size=24, origin="0, 4, 0", fov=30, up="0, 0, -1"))
    assert scene.lights.kind.tolist() == [LIGHT_DIRECTIONAL]
    img = _render(scene, 4 if direct == "nee" else 16, direct=direct)
    expect = 0.6 * np.array([3.0, 2.0, 1.0]) * 0.5 / math.pi
    np.testing.assert_allclose(img[4:-4, 4:-4].mean((0, 1)), expect, rtol=0.03)
    if direct == "nee":     # a delta light without occluders: every pixel exact
        np.testing.assert_allclose(img[4:-4, 4:-4], np.broadcast_to(expect, img[4:-4, 4:-4].shape), rtol=1e-4)


def _flux_through_square(scene, photons, half=0.25):
    """Flux per emitted photon crossing the square |x|, |z| < half in the
    plane y = 0 downward (photons start above it), over its area."""
    batch = emit_photon_jobs(scene, 7, np.arange(photons // 10_000), np.full(photons // 10_000, 10_000), 1e-6)
    o, d, f = (np.asarray(a, np.float64) for a in (batch.origin, batch.direction, batch.weight))
    t = -o[:, 1] / d[:, 1]
    hit = o + t[:, None] * d
    cross = (t > 0) & (d[:, 1] < 0) & (np.abs(hit[:, 0]) < half) & (np.abs(hit[:, 2]) < half)
    return f[cross].sum(0) / photons / (2 * half) ** 2


def test_directional_photons_give_its_irradiance_on_a_plane(tmp_path):
    """E cos(theta) crossing a plane, theta 60 degrees from its normal."""
    s = math.sin(math.radians(60))
    emitter = f"""<emitter type="directional"><vector name="direction" value="{s}, -0.5, 0"/>
        <rgb name="irradiance" value="3, 2, 1"/></emitter>"""
    scene = dp.load(mitsuba_scene(tmp_path, emitter, _sphere("0.5", radius=1.5)))
    flux = _flux_through_square(scene, 400_000)
    np.testing.assert_allclose(flux, np.array([3.0, 2.0, 1.0]) * 0.5, rtol=0.03)


def _irradiance_from_above(env, n=400):
    """The integral of L(w) max(0, w_y) over directions, by the midpoint rule."""
    theta = (np.arange(n) + 0.5) * (math.pi / 2) / n
    phi = (np.arange(2 * n) + 0.5) * math.pi / n
    total = np.zeros(3)
    for t in theta:
        w = math.sin(t) * (math.pi / 2 / n) * (math.pi / n) * math.cos(t)
        for p in phi:
            total += w * np.array(env_eval(env, math.sin(t) * math.cos(p), math.cos(t), math.sin(t) * math.sin(p)))
    return total


@needs_museum
def test_envmap_photons_give_its_irradiance_on_a_plane(tmp_path):
    """Photons of museum.exr (rotated) crossing a horizontal square carry
    the integral of L cos over the upper hemisphere."""
    emitter = f"""<emitter type="envmap"><string name="filename" value="{MUSEUM}"/><float name="scale" value="2"/>
        <transform name="to_world"><rotate x="0.6" z="0.8" angle="50"/></transform></emitter>"""
    scene = dp.load(mitsuba_scene(tmp_path, emitter, _sphere("0.5", radius=1.5)))
    expect = _irradiance_from_above(env_arrays(scene.lights), n=150)
    flux = _flux_through_square(scene, 1_000_000, half=0.4)
    np.testing.assert_allclose(flux, expect, rtol=0.04)


# -- the map's sampler ---------------------------------------------------------------------
def _synthetic_env(seed=4, h=7, w=12):
    rng = np.random.default_rng(seed)
    img = rng.uniform(0.05, 1.0, (h, w, 3)) ** 3
    img[2, 3:6] = 0.0        # a black band: its patches must never be sampled
    img[3, 3:6] = 0.0
    angle = 0.7
    c, s = math.cos(angle), math.sin(angle)
    rot = np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]]) @ np.array([[1, 0, 0], [0, c, -s], [0, s, c]])
    tex = texels_from_image(img)
    return (tex, rot, *distribution(tex))


def _patch_of(env, d):
    """The patch (row, column) of world direction d, as `env_pdf` finds it."""
    local = env[1].T @ d
    h1, w = env[4].shape
    u = (math.atan2(local[0], -local[2]) / (2 * math.pi) - 0.5 / w) % 1.0
    v = math.acos(max(-1.0, min(1.0, local[1]))) / math.pi
    return min(int(v * h1), h1 - 1), min(int(u * w), w - 1)


def test_envmap_pdf_integrates_to_one():
    env = _synthetic_env()
    h1, w = env[4].shape
    cos_t = np.cos(np.arange(h1 + 1) * math.pi / h1)
    solid = (2 * math.pi / w) * (cos_t[:-1] - cos_t[1:])
    assert abs((env[4] * solid[:, None]).sum() - 1) < 1e-12
    # The lookup, over uniform directions: E[pdf] 4 pi = 1.
    rng = np.random.default_rng(0)
    d = rng.normal(size=(200_000, 3))
    d /= np.linalg.norm(d, axis=1)[:, None]
    mean = np.mean([env_pdf(env, *x) for x in d]) * 4 * math.pi
    assert abs(mean - 1) < 0.01, mean


def test_envmap_samples_follow_their_pdf():
    """Chi-square of sampled patches against the pdf times solid angle;
    each sample's pdf is the lookup's; black patches are never drawn."""
    env = _synthetic_env()
    h1, w = env[4].shape
    cos_t = np.cos(np.arange(h1 + 1) * math.pi / h1)
    expect = env[4] * ((2 * math.pi / w) * (cos_t[:-1] - cos_t[1:]))[:, None]
    rng = np.random.default_rng(1)
    n = 200_000
    counts = np.zeros((h1, w))
    mismatched = 0
    for u1, u2 in rng.random((n, 2)):
        d0, d1, d2, pdf = env_sample(env, u1, u2)
        counts[_patch_of(env, np.array([d0, d1, d2]))] += 1
        mismatched += not math.isclose(pdf, env_pdf(env, d0, d1, d2), rel_tol=1e-9)
    assert mismatched < n * 1e-3          # a patch edge may round either way
    assert counts[expect == 0].sum() == 0
    live = expect > 0
    chi2 = ((counts[live] - n * expect[live]) ** 2 / (n * expect[live])).sum()
    dof = live.sum() - 1
    assert chi2 < dof + 5 * math.sqrt(2 * dof), (chi2, dof)


def test_envmap_sampling_prefers_bright_patches():
    """The pdf is the luminance of the patch over the map's integral."""
    env = _synthetic_env()
    lum = (0.25 * (env[0][:-1, :-1] + env[0][:-1, 1:] + env[0][1:, :-1] + env[0][1:, 1:])
           @ np.array([0.212671, 0.715160, 0.072169]))
    ratio = env[4][lum > 0] / lum[lum > 0]
    np.testing.assert_allclose(ratio, ratio[0], rtol=1e-5)


@needs_museum
def test_envmap_lookup_matches_mitsuba(mi):
    """Our bilinear lookup of museum.exr, rotated and scaled, against
    Mitsuba 3's envmap emitter in random directions."""
    axis = np.array([1.0, 2.0, 3.0]) / math.sqrt(14)
    to_world = mi.ScalarTransform4f().rotate(axis.tolist(), 40)
    emitter = mi.load_dict({"type": "envmap", "filename": MUSEUM, "scale": 2.0, "to_world": to_world})
    from dosppm_core.scene.envmap import load_image
    tex = texels_from_image(load_image(MUSEUM), 2.0)
    env = (tex, np.array(to_world.matrix)[:3, :3], *distribution(tex))
    rng = np.random.default_rng(1)
    for _ in range(500):
        d = rng.normal(size=3)
        d /= np.linalg.norm(d)
        si = mi.SurfaceInteraction3f()
        si.wi = mi.Vector3f(*(-d))
        theirs = np.array(emitter.eval(si))
        np.testing.assert_allclose(env_eval(env, *d), theirs, rtol=2e-3, atol=1e-4 * theirs.max())


# -- against Mitsuba 3 ---------------------------------------------------------------------
def _museum_scene(tmp_path, size=48):
    emitter = f"""<integrator type="path"/>
    <emitter type="envmap"><string name="filename" value="{MUSEUM}"/>
        <transform name="to_world"><rotate y="1" angle="70"/></transform></emitter>"""
    shapes = _sphere("0.7, 0.5, 0.3", centre="-0.55, 0, 0", radius=0.5) + """
    <shape type="sphere"><point name="center" value="0.55, 0, 0"/><float name="radius" value="0.5"/>
        <bsdf type="roughconductor"><string name="distribution" value="ggx"/><float name="alpha" value="0.15"/>
            <string name="material" value="none"/></bsdf></shape>
    <shape type="rectangle"><transform name="to_world"><scale value="2"/><rotate x="1" angle="-90"/>
        <translate y="-0.5"/></transform>
        <bsdf type="diffuse"><rgb name="reflectance" value="0.5"/></bsdf></shape>"""
    return mitsuba_scene(tmp_path, emitter, shapes, size=size, origin="0, 1.2, 3.5", fov=45,
                         name="museum.xml")


@pytest.mark.slow
@pytest.mark.reference
@needs_museum
def test_envmap_scene_matches_mitsuba(tmp_path, mi):
    """Two spheres (diffuse, rough conductor) on a floor under museum.exr,
    rotated: Mitsuba's path tracer reads the same file; the mean radiance
    agrees within 2%, each 12x12 tile's within 5%."""
    path = _museum_scene(tmp_path)
    theirs = np.asarray(mi.render(mi.load_file(path), spp=1024, seed=1), np.float64)[..., :3]
    ours = _render(dp.load(path), 160, photons_per_iteration=20_000)
    assert abs(ours.mean() / theirs.mean() - 1) < 0.02, (ours.mean(), theirs.mean())
    # Measured (seeds 3, 4): the mean within 0.5%, tiles within 2.2%.
    t_ours, t_theirs = (x.reshape(4, 12, 4, 12, 3).mean(axis=(1, 3, 4)) for x in (ours, theirs))
    rel = np.abs(t_ours / t_theirs - 1)
    assert rel.max() < 0.05, rel.max()


# -- chunks and the wire -------------------------------------------------------------------
@needs_museum
def test_chunked_envmap_render_equals_unchunked(tmp_path):
    """OSPPM over 8 chunks renders the museum scene as SPPM does, up to
    floating-point noise (eye rays missing the scene, leaving it through
    a chunk, shadow rays to the map, photons from its disc)."""
    assert_chunks_render_the_scene(dp.load(_museum_scene(tmp_path, size=32)), (2, 2, 2))


def test_chunked_plane_under_sun_and_sky_equals_unchunked(tmp_path):
    """A flat plane under a directional light and a constant sky: the
    scene's box has no height, so every shadow ray starts just outside it
    and every eye ray misses it or ends on the plane. Four chunks render
    what the whole scene does."""
    emitter = """<emitter type="directional"><vector name="direction" value="0.6, -0.8, 0"/>
        <rgb name="irradiance" value="2"/></emitter>
        <emitter type="constant"><rgb name="radiance" value="0.3, 0.4, 0.5"/></emitter>"""
    plane = """<shape type="rectangle"><transform name="to_world"><scale value="2"/><rotate x="1" angle="-90"/>
        </transform><bsdf type="diffuse"><rgb name="reflectance" value="0.6"/></bsdf></shape>"""
    scene = dp.load(mitsuba_scene(tmp_path, emitter, plane, size=24, origin="0, 3, 0", fov=40, up="0, 0, -1"))
    assert sorted(scene.lights.kind.tolist()) == [LIGHT_DIRECTIONAL, LIGHT_ENV]
    # The box exactly the scene's (no margin): shadow rays spawned off the
    # plane start outside it, and must still reach their lights.
    assert_chunks_render_the_scene(scene, (2, 1, 2), box=scene.bounds())
    # The plane fills the view: (E cos + pi L_sky) albedo / pi.
    img = np.asarray(dp.render(scene, iterations=64, mode="sppm", seed=1, photons_per_iteration=10_000))
    expect = 0.6 * (2 * 0.8 / math.pi + np.array([0.3, 0.4, 0.5]))
    np.testing.assert_allclose(img.mean((0, 1)), expect, rtol=0.02)


@needs_museum
def test_header_carries_the_environment_over_the_wire(tmp_path):
    scene = dp.load(_museum_scene(tmp_path, size=16))
    wire = msgpack.unpackb(msgpack.packb(scene.header().to_wire()))
    header = SceneHeader.from_wire(wire)
    a, b = scene.lights, header.lights
    for name, value in a.wire_fields().items():
        np.testing.assert_array_equal(getattr(b, name), value, err_msg=name)
    assert b.kind[-1] == LIGHT_ENV and b.env_texels.shape == (256, 513, 3)
    assert environment(b).p_select == pytest.approx(environment(a).p_select)


def test_two_environments_are_refused(tmp_path):
    path = mitsuba_scene(tmp_path, '<emitter type="constant"/>\n<emitter type="constant"/>', _sphere("0.5"))
    with pytest.raises(SceneError, match=r"scene.xml:3: <emitter type=\"constant\">: only one environment"):
        dp.load(path)


@needs_museum
def test_envmap_must_be_rotated_not_scaled(tmp_path):
    emitter = f"""<emitter type="envmap"><string name="filename" value="{MUSEUM}"/>
        <transform name="to_world"><scale value="2"/></transform></emitter>"""
    with pytest.raises(SceneError, match="rotation only"):
        dp.load(mitsuba_scene(tmp_path, emitter, _sphere("0.5")))


@needs_shared_scenes
@pytest.mark.parametrize("name", ["bsdf_spheres/test_envmap_path.xml", "bsdf_spheres/test_constant_path.xml",
                                  "floating_sphere/test_directional_direct.xml", "infinite_mirrors/scene_path.xml"])
def test_mitsuba_test_scenes_get_past_their_emitter(name):
    """Mitsuba's own test scenes with these emitters load, or stop at
    something else (textures, materials), not at the emitter."""
    path = os.path.join(MITSUBA_DATA, "tests", "scenes", name)
    try:
        dp.load(path)
    except SceneError as e:
        assert "<emitter" not in str(e), str(e)


# -- through the render service ------------------------------------------------------------
@pytest.mark.slow
@needs_museum
def test_render_service_with_two_chunks_renders_the_envmap_scene(tmp_path):
    """`dosppm render scene.xml --chunks 2` (a server and two tracer
    processes): the tracers get the map in the scene header, and the image
    equals single-process SPPM within the noise between two seeds."""
    from dosppm_core.film import read_exr
    from tests.helpers.cli import run_dosppm
    from tests.helpers.cluster import ITERATIONS, assert_same_within_noise, settings
    path = _museum_scene(tmp_path, size=32)
    out = tmp_path / "img.exr"
    proc = run_dosppm("render", path, "--chunks", "2", "--tracers", "2", "--photons", "240000",
                      "--photons-per-iteration", "40000", "--seed", "5", "--threads", "1",
                      "--min-photon-jobs", "16", "--http", "off", "--out", str(out),
                      "--store-cache", str(tmp_path / "stores"), timeout=400)
    assert proc.returncode == 0, proc.stderr[-3000:]
    img = read_exr(str(out))[0]
    scene = dp.load(path)
    refs = {}
    for seed in (5, 9):
        r = Renderer(scene, settings(seed))
        for _ in range(ITERATIONS):
            r.run_iteration()
        refs[seed] = r.image()
        r.close()
    assert_same_within_noise(img, refs[5], refs[9])


@needs_museum
def test_toml_environment_reads_as_the_xml_envmap(tmp_path):
    """The TOML `environment` light (file, scale, rotate) and `directional`
    give the light table Mitsuba's XML does."""
    shapes_xml = _sphere("0.5")
    xml = dp.load(mitsuba_scene(tmp_path, f"""
        <emitter type="envmap"><string name="filename" value="{MUSEUM}"/>
        <float name="scale" value="1.5"/><transform name="to_world"><rotate y="1" angle="30"/></transform></emitter>
        <emitter type="directional"><vector name="direction" value="0, -1, 0"/><rgb name="irradiance" value="2"/>
        </emitter>""", shapes_xml))
    toml = tmp_path / "scene.toml"
    toml.write_text(f"""[camera]
position = [0, 0.3, 4]
look_at = [0, 0, 0]
up = [0, 1, 0]
fov = 35
width = 32
height = 32

[materials.grey]
type = "diffuse"
reflectance = 0.5

[[shapes]]
type = "sphere"
material = "grey"
scale = 0.8

[[lights]]
type = "environment"
file = "{MUSEUM}"
scale = 1.5
rotate = [0, 1, 0, 30]

[[lights]]
type = "directional"
direction = [0, -1, 0]
irradiance = 2
""")
    ours = dp.load(str(toml))
    a, b = xml.lights, ours.lights
    np.testing.assert_array_equal(a.env_texels, b.env_texels)
    np.testing.assert_allclose(a.env_to_world, b.env_to_world, atol=1e-12)
    assert sorted(a.kind.tolist()) == sorted(b.kind.tolist()) == [LIGHT_DIRECTIONAL, LIGHT_ENV]
    np.testing.assert_allclose(np.sort(a.power), np.sort(b.power), rtol=1e-3)   # spheres of like radius


@needs_museum
@pytest.mark.parametrize("floor", ["diffuse", "glossy"])
def test_lights_add_up_with_an_environment_and_an_area_light(tmp_path, floor):
    """Light is linear: a scene under museum.exr and a lamp renders the
    sum of the two lit apart. Mixed, shadow rays choose between infinite
    and tree-sampled lights (diffuse floor), or by power with MIS against
    the BSDF (glossy floor: both the map and the lamp are found by BSDF
    rays too); each estimate divides by its own mixture."""
    bsdf = ('<bsdf type="diffuse"><rgb name="reflectance" value="0.6"/></bsdf>' if floor == "diffuse" else
            '<bsdf type="roughconductor"><string name="distribution" value="ggx"/>'
            '<float name="alpha" value="0.3"/><string name="material" value="none"/></bsdf>')
    lamp = """<shape type="rectangle"><transform name="to_world"><scale value="0.3"/><rotate x="1" angle="90"/>
        <translate y="1.2"/></transform><emitter type="area"><rgb name="radiance" value="8"/></emitter></shape>"""
    env = f'<emitter type="envmap"><string name="filename" value="{MUSEUM}"/></emitter>'
    base = f"""<shape type="rectangle"><transform name="to_world"><scale value="2"/><rotate x="1" angle="-90"/>
        <translate y="-0.5"/></transform>{bsdf}</shape>""" + _sphere("0.5", radius=0.5)
    images = {}
    for name, emitter, shapes in (("both", env, base + lamp), ("env", env, base), ("lamp", "", base + lamp)):
        path = mitsuba_scene(tmp_path, emitter, shapes, size=32, origin="0, 1.5, 3", fov=50,
                             name=f"{name}.xml")
        images[name] = _render(dp.load(path), 48, photons_per_iteration=20_000)
    summed = images["env"] + images["lamp"]
    assert abs(images["both"].mean() / summed.mean() - 1) < 0.02
    t_both, t_sum = (x.reshape(4, 8, 4, 8, 3).mean(axis=(1, 3, 4)) for x in (images["both"], summed))
    assert np.abs(t_both / t_sum - 1).max() < 0.06


# -- the projector -------------------------------------------------------------------------
PROJECTOR = """<emitter type="projector"><float name="fov" value="90"/><rgb name="irradiance" value="0.5, 1, 2"/>
    <transform name="to_world"><lookat origin="0, 1, 0" target="0, 0, 0" up="0, 0, 1"/></transform></emitter>"""


def test_projector_photons_give_pi_e_on_its_image_plane(tmp_path):
    """Mitsuba's projector: its image plane at distance 1 (here y = 0,
    |x|, |z| < 1 for a 90 degree fov) receives pi E, nothing outside."""
    scene = dp.load(mitsuba_scene(tmp_path, PROJECTOR, _sphere("0.5", radius=1.5)))
    inside = _flux_through_square(scene, 200_000, half=0.9)
    np.testing.assert_allclose(inside, math.pi * np.array([0.5, 1.0, 2.0]), rtol=0.03)
    ring = _flux_through_square(scene, 200_000, half=1.5) * 9 - _flux_through_square(scene, 200_000, half=1.0) * 4
    np.testing.assert_allclose(ring, 0.0, atol=1e-9)


@pytest.mark.parametrize("direct", ["nee", "photons"])
def test_projector_on_a_diffuse_plane(tmp_path, direct):
    """A plane of albedo a at distance 1: radiance a E inside the frustum's
    footprint, 0 outside it."""
    plane = """<shape type="rectangle"><transform name="to_world"><scale value="1.6"/><rotate x="1" angle="-90"/>
        </transform><bsdf type="diffuse"><rgb name="reflectance" value="0.6"/></bsdf></shape>"""
    scene = dp.load(mitsuba_scene(tmp_path, PROJECTOR, plane, size=32, origin="0, 3, 0", fov=60,
                                  up="0, 0, 1"))
    img = _render(scene, 16, direct=direct)
    # The view spans |x| < 3 tan 30 = 1.73: the footprint |x| < 1 is the middle 58%.
    mid, rim = img[10:22, 10:22], np.concatenate([img[:, :3], img[:, -3:]])
    np.testing.assert_allclose(mid.mean((0, 1)), 0.6 * np.array([0.5, 1.0, 2.0]), rtol=0.03)
    assert rim.max() < (1e-6 if direct == "nee" else 0.05)


@needs_shared_scenes
def test_mitsuba_projector_scene_matches_its_reference():
    """Mitsuba's test_projector_constant_direct (a plane, no indirect
    light): the mean of its reference image within 1% with shadow rays."""
    from dosppm_core.film import read_exr
    folder = os.path.join(MITSUBA_DATA, "tests", "scenes", "projector")
    ref = read_exr(os.path.join(folder, "refs", "test_projector_constant_ref_rgb.exr"))[0]
    img = _render(dp.load(os.path.join(folder, "test_projector_constant_direct.xml")), 8)
    np.testing.assert_allclose(img.mean((0, 1)), ref.mean((0, 1)), rtol=0.01)


def test_environment_photons_are_culled_at_the_hit_point_box(tmp_path):
    """A close view of the sphere under a constant sky: most photons from
    the sky's disc land outside the hit points' box and are culled, and the
    image is the one rendered with every photon kept (culling drops only
    deposits no hit point could gather)."""
    floor = """<shape type="rectangle"><transform name="to_world"><scale value="6"/><rotate x="1" angle="-90"/>
        <translate y="-0.8"/></transform><bsdf type="diffuse"><rgb name="reflectance" value="0.5"/></bsdf></shape>"""
    scene = dp.load(mitsuba_scene(tmp_path, '<emitter type="constant"/>', _sphere("0.6") + floor, size=16,
                         origin="0, 0, 2.5", fov=20))
    images = {}
    for cull in (True, False):
        r = Renderer(scene, RenderSettings(seed=2, photons_per_iteration=20_000, cull=cull))
        for _ in range(3):
            r.run_iteration()
        images[cull] = r.image()
        if cull:    # most of an iteration's deposits fall outside the box
            jobs = [emit_photon_job(scene, 2, 99, 20_000, r.surf.eps_abs)]
            deposits, _ends, culled = trace_photon_jobs(r.accel, r.surf, jobs, r.sppm.cull_box(), 256, 1)
            assert culled > 2 * len(deposits) > 0
        r.close()
    np.testing.assert_allclose(images[True], images[False], rtol=1e-5, atol=1e-7)


def test_server_starts_infinite_light_photons_in_every_chunk(tmp_path):
    """Photons of a sky enter the scene anywhere: every chunk's tracers
    emit (a lamp's photons start in its own chunk)."""
    from services.server.balance import light_chunks
    lamp = """<shape type="rectangle"><transform name="to_world"><scale value="0.2"/><rotate x="1" angle="90"/>
        <translate x="0.5" y="1" z="0.5"/></transform><emitter type="area"><rgb name="radiance" value="1"/>
        </emitter></shape>"""
    for emitter, expect in (("", [7]), ('<emitter type="constant"/>', list(range(8)))):
        scene = dp.load(mitsuba_scene(tmp_path, emitter, _sphere("0.5") + lamp, name=f"{len(expect)}.xml"))
        tree = uniform_tree(root_box(scene), (2, 2, 2))
        assert light_chunks(scene.header(), tree) == expect


@pytest.mark.reference
@needs_museum
def test_reference_renderer_maps_the_new_lights_to_mitsuba(tmp_path):
    """`dosppm reference` hands our scene to Mitsuba: the rotated envmap,
    a directional light and a projector come out as Mitsuba reads the same
    file (means within 1.5%, both at 64 spp)."""
    mi = pytest.importorskip("mitsuba")
    from harness.reference import render_reference
    emitter = f"""<integrator type="path"/>
    <emitter type="envmap"><string name="filename" value="{MUSEUM}"/><float name="scale" value="0.5"/>
        <transform name="to_world"><rotate x="0.6" y="0.8" angle="35"/></transform></emitter>
    <emitter type="directional"><vector name="direction" value="0.3, -1, 0.2"/><rgb name="irradiance" value="1, 0.8, 0.6"/>
    </emitter>
    <emitter type="projector"><float name="fov" value="30"/><rgb name="irradiance" value="3, 6, 9"/>
        <transform name="to_world"><lookat origin="1, 2, 1" target="0, -0.5, 0" up="0, 1, 0"/></transform></emitter>"""
    floor = """<shape type="rectangle"><transform name="to_world"><scale value="3"/><rotate x="1" angle="-90"/>
        <translate y="-0.8"/></transform><bsdf type="diffuse"><rgb name="reflectance" value="0.5"/></bsdf></shape>"""
    path = mitsuba_scene(tmp_path, emitter, _sphere("0.6, 0.5, 0.4") + floor, size=24, origin="0, 1.5, 4",
                         fov=45)
    mi.set_variant("scalar_rgb")
    theirs = np.asarray(mi.render(mi.load_file(path), spp=64, seed=1), np.float64)[..., :3]
    mapped = render_reference(dp.load(path), spp=64, seed=2)
    np.testing.assert_allclose(mapped.mean((0, 1)), theirs.mean((0, 1)), rtol=0.015)
