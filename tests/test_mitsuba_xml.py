"""The Mitsuba 3 / Nori XML importer, checked against the shared scenes and,
where it is installed, against Mitsuba itself (scalar_rgb)."""
import os
import textwrap
import warnings

import numpy as np
import pytest

from dosppm_core.scene.mitsuba import load_mitsuba_xml
from dosppm_core.scene.mitsuba.bsdfs import IORS
from dosppm_core.scene.model import LIGHT_POINT, LIGHT_SPOT, LIGHT_TRIANGLE, SceneError
from tests.helpers.paths import SHARED_SCENES, needs_shared_scenes

CBOX = os.path.join(SHARED_SCENES, "cornell_box", "mitsuba")
NORI = os.path.join(SHARED_SCENES, "cbox_glass_mirror_spheres_nori", "cbox-pmap.xml")


def write(tmp_path, text, name="scene.xml"):
    path = tmp_path / name
    path.write_text(textwrap.dedent(text).lstrip("\n"))
    return str(path)


def material(scene, name):
    return scene.materials.names.index(name)


def triangles_of(scene, material_id):
    """(n, 3, 3) world positions of the triangles using one material."""
    return scene.vertices[scene.triangles[scene.tri_material == material_id]].astype(np.float64)


def normals(tris):
    n = np.cross(tris[:, 1] - tris[:, 0], tris[:, 2] - tris[:, 0])
    return n / np.linalg.norm(n, axis=1, keepdims=True)


# -- the measured Cornell box ------------------------------------------------

@needs_shared_scenes
def test_cbox_geometry_and_light():
    scene = load_mitsuba_xml(os.path.join(CBOX, "cbox.xml"))
    assert scene.triangle_count == 38                 # 8 OBJ parts, SOURCE.md
    np.testing.assert_allclose(scene.bounds(), [[0, 0, 0], [556, 548.8, 559.2]], atol=1e-3)
    emissive = np.flatnonzero(scene.materials.emission.max(axis=1) > 0)
    assert len(emissive) == 1
    assert np.all(scene.lights.kind == LIGHT_TRIANGLE) and len(scene.lights.kind) == 2
    light = triangles_of(scene, emissive[0])
    np.testing.assert_allclose(normals(light), [[0, -1, 0]] * 2, atol=1e-6)  # faces the floor
    np.testing.assert_allclose(light[..., 1], 548.3, atol=1e-3)              # translated by -0.5
    assert np.all(scene.materials.emission[emissive[0]] > 1)


@needs_shared_scenes
def test_cbox_camera_materials_and_settings():
    scene = load_mitsuba_xml(os.path.join(CBOX, "cbox.xml"))
    cam = scene.camera
    np.testing.assert_allclose(cam.position, (278, 273, -800))
    np.testing.assert_allclose(cam.look_at, (278, 273, -799))
    np.testing.assert_allclose(cam.up, (0, 1, 0))
    assert (cam.fov_deg, cam.fov_axis, cam.width, cam.height) == (39.3077, "smaller", 256, 256)
    assert (cam.near_clip, cam.focus_distance, cam.aperture_radius) == (10, 1000, 0)
    assert scene.render_settings == {"integrator": "path", "max_depth": 6, "spp": 128,
                                     "sampler": "independent", "far_clip": 2800.0,
                                     "rfilter": {"type": "gaussian"}}
    names = scene.materials.names
    assert {"white", "red", "green", "box"} <= set(names)
    assert sum(n.startswith("light+") for n in names) == 1
    assert np.all(scene.materials.kind == 0) and not np.any(scene.materials.two_sided)


def mitsuba_colours(mi, path):
    """{bsdf id: reflectance} and {bsdf id: radiance} as Mitsuba loads them."""
    reflectance, radiance = {}, {}
    for shape in mi.load_file(path).shapes():
        bsdf = shape.bsdf()
        reflectance[bsdf.id()] = np.array(mi.traverse(bsdf)["reflectance.value"], float)
        if shape.emitter() is not None:
            radiance[bsdf.id()] = np.array(mi.traverse(shape.emitter())["radiance.value"], float)
    return reflectance, radiance


@pytest.mark.reference
@needs_shared_scenes
@pytest.mark.parametrize("name", ["cbox.xml", "cbox-rgb.xml"])
def test_cbox_colours_match_mitsuba(mi, name):
    path = os.path.join(CBOX, name)
    scene = load_mitsuba_xml(path)
    reflectance, radiance = mitsuba_colours(mi, path)
    assert len(reflectance) >= 4 and len(radiance) == 1
    by_bsdf = {n.split("+")[0]: i for i, n in enumerate(scene.materials.names)}
    for bsdf_id, rgb in reflectance.items():
        np.testing.assert_allclose(scene.materials.reflectance[by_bsdf[bsdf_id]], rgb, rtol=1e-5)
    for bsdf_id, rgb in radiance.items():
        np.testing.assert_allclose(scene.materials.emission[by_bsdf[bsdf_id]], rgb, rtol=1e-5)


@needs_shared_scenes
def test_cbox_rgb_includes_and_overrides():
    scene = load_mitsuba_xml(os.path.join(CBOX, "cbox-rgb.xml"), res=64, spp=8)
    assert (scene.camera.width, scene.camera.height) == (64, 64)
    assert scene.render_settings["spp"] == 8 and scene.render_settings["rfilter"] == {"type": "box"}
    assert scene.triangle_count == 38
    np.testing.assert_allclose(scene.materials.reflectance[material(scene, "box")], (0.45, 0.3, 0.9), rtol=1e-6)
    np.testing.assert_allclose(scene.materials.emission[material(scene, "light+area-emitter")],
                               (18.387, 10.9873, 2.75357), rtol=1e-6)


@needs_shared_scenes
def test_ply_with_transform(tmp_path):
    ply = os.path.join(SHARED_SCENES, "cornell_box", "cbox_merged.ply")
    path = write(tmp_path, TEMPLATE.format(snippet=f"""
        <shape type="ply">
            <string name="filename" value="{ply}"/><boolean name="face_normals" value="true"/>
            <transform name="to_world"><scale value="0.001"/><translate x="5"/></transform>
        </shape>"""))
    scene = load_mitsuba_xml(path)
    tris = triangles_of(scene, material(scene, "default"))
    assert len(tris) == 38
    np.testing.assert_allclose(tris.reshape(-1, 3).min(axis=0), (5, 0, 0), atol=1e-6)
    np.testing.assert_allclose(tris.reshape(-1, 3).max(axis=0), (5.556, 0.5488, 0.5592), atol=1e-6)


# -- $name defaults ------------------------------------------------------------

DEFAULTS_SCENE = """
    <scene version="3.0.0">
        <default name="res" value="32"/>
        <default name="resolution" value="7"/>
        <sensor type="perspective">
            <film type="hdrfilm">
                <integer name="width" value="$resolution"/>
                <integer name="height" value="$res"/>
            </film>
        </sensor>
        <shape type="cube">
            <emitter type="area"><rgb name="radiance" value="$glow"/></emitter>
        </shape>
    </scene>
"""


def test_defaults_and_overrides(tmp_path):
    path = write(tmp_path, DEFAULTS_SCENE.replace("$glow", "2"))
    scene = load_mitsuba_xml(path)
    assert (scene.camera.width, scene.camera.height) == (7, 32)   # $resolution is not $res + "olution"
    scene = load_mitsuba_xml(path, res=16, resolution=9)
    assert (scene.camera.width, scene.camera.height) == (9, 16)
    with pytest.raises(SceneError, match="never used"):
        load_mitsuba_xml(path, spp=4)
    path = write(tmp_path, DEFAULTS_SCENE, name="glow.xml")
    assert load_mitsuba_xml(path, glow=3).materials.emission.max() == 3
    with pytest.raises(SceneError, match=r"glow\.xml:11: <rgb name=\"radiance\">: undefined parameter"):
        load_mitsuba_xml(path)


# -- every supported plugin, against Mitsuba -----------------------------------

FEATURES = """
    <scene version="3.0.0">
        <sensor type="thinlens">
            <string name="focal_length" value="35mm"/>
            <float name="aperture_radius" value="0.05"/>
            <float name="focus_distance" value="7"/>
            <transform name="to_world">
                <lookat origin="1, 2, -8" target="0, 0.5, 0" up="0, 1, 0"/>
            </transform>
            <film type="hdrfilm"><integer name="width" value="40"/><integer name="height" value="30"/></film>
        </sensor>
        <shape type="rectangle" id="lamp">
            <transform name="to_world">
                <rotate x="1" angle="90"/><scale value="0.5"/><translate y="3"/>
            </transform>
            <bsdf type="diffuse" id="lamp_bsdf"/>
            <emitter type="area" id="glow"><spectrum name="radiance" value="4"/></emitter>
        </shape>
        <shape type="rectangle" id="mirrored">
            <transform name="to_world"><scale x="-1"/><translate z="4"/></transform>
            <bsdf type="conductor" id="mirror_bsdf"><rgb name="specular_reflectance" value="0.9"/></bsdf>
        </shape>
        <shape type="rectangle" id="flipped">
            <boolean name="flip_normals" value="true"/>
            <transform name="to_world"><translate x="3" z="1"/></transform>
            <bsdf type="roughconductor" id="rough_bsdf">
                <string name="distribution" value="ggx"/><float name="alpha" value="0.3"/>
            </bsdf>
        </shape>
        <shape type="cube" id="box">
            <transform name="to_world">
                <scale x="0.5" y="1" z="2"/><rotate value="0, 1, 1" angle="30"/><translate x="-2"/>
            </transform>
            <bsdf type="twosided" id="box_bsdf">
                <bsdf type="diffuse">
                    <spectrum name="reflectance" value="400:0.2, 500:0.7, 600:0.4, 700:0.9"/>
                </bsdf>
            </bsdf>
        </shape>
        <shape type="obj" id="tri">
            <string name="filename" value="tri.obj"/>
            <transform name="to_world">
                <matrix value="0 -1 0 1  1 0 0 2  0 0 1 3  0 0 0 1"/><scale value="2"/>
            </transform>
            <bsdf type="dielectric" id="glass_bsdf">
                <string name="int_ior" value="water"/><float name="ext_ior" value="1.1"/>
            </bsdf>
        </shape>
        <shape type="sphere" id="ball">
            <point name="center" x="1" y="1" z="1"/><float name="radius" value="0.5"/>
            <transform name="to_world"><scale z="-1"/><translate x="2"/></transform>
            <bsdf type="dielectric" id="ball_bsdf"/>
        </shape>
        <emitter type="point" id="bulb">
            <point name="position" value="0, 4, 0"/>
            <spectrum name="intensity" value="450:1, 550:3, 650:2"/>
        </emitter>
        <emitter type="spot" id="spot">
            <transform name="to_world"><lookat origin="0, 5, 0" target="0, 0, 0" up="1, 0, 0"/></transform>
            <rgb name="intensity" value="5, 4, 3"/>
            <float name="cutoff_angle" value="30"/>
            <float name="beam_width" value="20"/>
        </emitter>
    </scene>
"""


@pytest.fixture
def features(tmp_path):
    (tmp_path / "tri.obj").write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nv 1 1 0\nf 1 2 3\nf 2 4 3\n")
    return write(tmp_path, FEATURES)


@pytest.mark.reference
def test_features_match_mitsuba(mi, features):
    scene = load_mitsuba_xml(features)
    ref = mi.load_file(features)
    params = mi.traverse(ref)
    shapes = {s.id(): s for s in ref.shapes()}
    mats = scene.materials
    for shape_id, bsdf in (("box", "box_bsdf"), ("tri", "glass_bsdf")):
        ours = np.unique(triangles_of(scene, material(scene, bsdf)).reshape(-1, 3).round(4), axis=0)
        theirs = np.array(params[f"{shape_id}.vertex_positions"], float).reshape(-1, 3)
        np.testing.assert_allclose(ours, np.unique(theirs.round(4), axis=0), atol=2e-4)
    np.testing.assert_allclose(mats.reflectance[material(scene, "box_bsdf")],
                               mi.traverse(shapes["box"].bsdf())["brdf_0.reflectance.value"], rtol=1e-5)
    for shape_id, bsdf in (("tri", "glass_bsdf"), ("ball", "ball_bsdf")):
        eta = mi.traverse(shapes[shape_id].bsdf())["eta"]
        np.testing.assert_allclose(mats.ior[material(scene, bsdf)], eta, rtol=1e-6)
    np.testing.assert_allclose(mats.emission[material(scene, "lamp_bsdf+glow")],
                               params["lamp.emitter.radiance.value"], rtol=1e-5)
    rough, mirror = material(scene, "rough_bsdf"), material(scene, "mirror_bsdf")
    assert mats.kind[rough] == 3 and mats.roughness[rough] == pytest.approx(0.3)
    assert mats.kind[mirror] == 1 and mats.reflectance[mirror] == pytest.approx([0.9] * 3)
    assert mats.two_sided[material(scene, "box_bsdf")] and not mats.two_sided[mirror]
    check_lights(scene, params)
    check_front_sides(mi, scene, ref)
    check_sphere(scene, params)
    check_camera(mi, scene, ref)


def check_lights(scene, params):
    lights = scene.lights
    point, spot = (np.flatnonzero(lights.kind == k)[0] for k in (LIGHT_POINT, LIGHT_SPOT))
    np.testing.assert_allclose(lights.p0[point], params["bulb.position"])
    np.testing.assert_allclose(lights.value[point], params["bulb.intensity.value"], rtol=1e-5)
    np.testing.assert_allclose(lights.value[spot], params["spot.intensity.value"], rtol=1e-6)
    to_world = np.array(params["spot.to_world"].matrix, float)
    np.testing.assert_allclose(lights.p0[spot], to_world[:3, 3], atol=1e-6)
    np.testing.assert_allclose(lights.p1[spot], to_world[:3, 2], atol=1e-6)
    np.testing.assert_allclose(np.degrees(lights.cone[spot, 2:]),
                               (params["spot.cutoff_angle"], params["spot.beam_width"]), rtol=1e-6)


def check_front_sides(mi, scene, ref):
    """The side our winding faces is the side Mitsuba's BSDFs and emitters
    treat as the front (its shading normal, which can differ from its
    geometric one under a mirroring transform)."""
    for bsdf in ("lamp_bsdf+glow", "mirror_bsdf", "rough_bsdf", "box_bsdf", "ball_bsdf"):
        tris = triangles_of(scene, material(scene, bsdf))
        for tri, normal in list(zip(tris, normals(tris)))[::max(1, len(tris) // 12)]:
            # Off-centre, so the ray cannot graze an edge of Mitsuba's own triangulation.
            origin = np.array([0.5, 0.3, 0.2]) @ tri + 0.01 * normal
            si = ref.ray_intersect(mi.Ray3f(mi.Point3f(*origin), mi.Vector3f(*(-normal))))
            assert bool(si.is_valid()) and float(si.t) < 0.02, bsdf
            assert float(np.dot(np.array(si.sh_frame.n, float), normal)) > 0.99, bsdf


def check_sphere(scene, params):
    m = np.array(params["ball.to_world"].matrix, float)
    tris = triangles_of(scene, material(scene, "ball_bsdf"))
    local = (tris.reshape(-1, 3) - m[:3, 3]) @ np.linalg.inv(m[:3, :3]).T
    np.testing.assert_allclose(np.linalg.norm(local, axis=1), 1.0, atol=1e-5)
    assert len(tris) == 20480
    inward = np.einsum("ij,ij->i", normals(tris), tris.mean(axis=1) - m[:3, 3]) < 0
    assert np.all(inward)                 # mirrored by scale z=-1, as Mitsuba turns it


def check_camera(mi, scene, ref):
    """Mitsuba's ray through image point (u, v) (v down, lens centre) must be
    ours: forward + (2u - 1) tan_x right + (1 - 2v) tan_y up."""
    cam = scene.camera
    position, right, up, forward, (tan_x, tan_y, _), _ = cam.frame()[:6]
    sensor = ref.sensors()[0]
    for u, v in ((0.5, 0.5), (0.9, 0.2), (0.1, 0.95)):
        ray, _ = sensor.sample_ray(0.0, 0.5, mi.Point2f(u, v), mi.Point2f(0.5, 0.5))
        ours = forward + (2 * u - 1) * tan_x * right + (1 - 2 * v) * tan_y * up
        np.testing.assert_allclose(np.array(ray.d, float), ours / np.linalg.norm(ours), atol=1e-5)
        # Mitsuba starts the ray on the near plane, on the same line.
        np.testing.assert_allclose(np.cross(np.array(ray.o, float) - position, ours), 0, atol=1e-5)
    params = mi.traverse(sensor)
    assert cam.aperture_radius == pytest.approx(params["aperture_radius"]) and cam.focus_distance == 7


SPECTRA = ["0.5", "400:0.2, 700:0.8", "500:0, 530:1, 560:0", "300:0.3, 900:0.6", "380:1, 420:0.1, 780:0.4"]


@pytest.mark.reference
@pytest.mark.parametrize("spectrum", SPECTRA)
def test_spectra_match_mitsuba(mi, tmp_path, spectrum):
    """Reflectance (D65-weighted, clamped to [0, 1]) and radiance (neither)."""
    path = write(tmp_path, f"""
        <scene version="3.0.0">
            <sensor type="perspective"/>
            <shape type="rectangle">
                <bsdf type="diffuse" id="paint"><spectrum name="reflectance" value="{spectrum}"/></bsdf>
                <emitter type="area"><spectrum name="radiance" value="{spectrum}"/></emitter>
            </shape>
        </scene>""")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")           # out-of-gamut spectra warn, as in Mitsuba
        scene = load_mitsuba_xml(path)
    reflectance, radiance = mitsuba_colours(mi, path)
    np.testing.assert_allclose(scene.materials.reflectance[0], reflectance["paint"], rtol=1e-5, atol=1e-7)
    np.testing.assert_allclose(scene.materials.emission[0], radiance["paint"], rtol=1e-5, atol=1e-7)


@pytest.mark.reference
def test_named_iors_match_mitsuba(mi, tmp_path):
    for name, value in IORS.items():
        bsdf = mi.load_dict({"type": "dielectric", "int_ior": name, "ext_ior": "vacuum"})
        assert mi.traverse(bsdf)["eta"] == pytest.approx(value, rel=1e-6), name


# -- Nori's format ---------------------------------------------------------------

@needs_shared_scenes
def test_nori_scene():
    scene = load_mitsuba_xml(NORI)
    assert scene.triangle_count == 2188
    cam = scene.camera
    np.testing.assert_allclose(cam.position, (0, 0.919769, 5.41159))
    forward = np.subtract((0, 0.893051, 4.41198), cam.position)
    np.testing.assert_allclose(np.subtract(cam.look_at, cam.position), forward / np.linalg.norm(forward))
    assert (cam.fov_deg, cam.fov_axis, cam.width, cam.height) == (27.7856, "x", 1024, 768)
    assert cam.frame()[1][0] > 0.99          # red wall (x = -1) on the left, as Nori renders it
    kinds = dict(zip(scene.materials.names, scene.materials.kind))
    assert sorted(kinds.values()) == [0, 0, 0, 0, 1, 2]
    glass = list(scene.materials.kind).index(2)
    assert scene.materials.ior[glass] == pytest.approx(1.5046 / 1.000277)
    np.testing.assert_allclose(scene.materials.emission.max(axis=0), (15, 15, 15))
    assert scene.render_settings == {"integrator": "photonmapper", "photon_radius": 0.05,
                                     "photon_count": 10_000_000, "sampler": "independent",
                                     "spp": 32, "far_clip": 1e4}


def test_nori_unmirrored_camera_is_refused(tmp_path):
    path = write(tmp_path, """
        <scene>
            <camera type="perspective">
                <transform name="toWorld"><lookat origin="0,0,5" target="0,0,0" up="0,1,0"/></transform>
            </camera>
            <mesh type="obj"><string name="filename" value="t.obj"/></mesh>
        </scene>""")
    with pytest.raises(SceneError, match=r"scene\.xml:3: <transform name=\"toWorld\">: .*mirrors.*Nori"):
        load_mitsuba_xml(path)


def test_mitsuba_06_camel_case_is_upgraded(tmp_path):
    path = write(tmp_path, """
        <scene version="0.6.0">
            <integrator type="path"><integer name="maxDepth" value="3"/></integrator>
            <sensor type="perspective">
                <transform name="toWorld"><lookAt origin="0,0,-5" target="0,0,0" up="0,1,0"/></transform>
                <sampler type="independent"><integer name="sampleCount" value="9"/></sampler>
            </sensor>
            <shape type="cube">
                <bsdf type="diffuse"><rgb name="diffuseReflectance" value="0.25"/></bsdf>
                <emitter type="area"><rgb name="radiance" value="1"/></emitter>
            </shape>
        </scene>""")
    scene = load_mitsuba_xml(path)
    assert scene.render_settings["max_depth"] == 3 and scene.render_settings["spp"] == 9
    np.testing.assert_allclose(scene.materials.reflectance[0], 0.25)
    np.testing.assert_allclose(scene.camera.position, (0, 0, -5))


# -- errors: one line naming file:line and the element ---------------------------

TEMPLATE = """\
<scene version="3.0.0">
    <sensor type="perspective">
        <float name="fov" value="40"/>
        <transform name="to_world"><lookat origin="0,0,-5" target="0,0,0" up="0,1,0"/></transform>
        <film type="hdrfilm"><integer name="width" value="8"/><integer name="height" value="8"/></film>
    </sensor>
    <shape type="rectangle">
        <emitter type="area"><rgb name="radiance" value="1"/></emitter>
    </shape>
{snippet}
</scene>
"""
SNIPPET_LINE = 10

BAD = [  # (snippet, line offset, element as written, what the message says)
    ('<bsdf type="hair" id="p"/>', 0, '<bsdf type="hair" id="p">', "unsupported plugin"),
    ('<bsdf type="principled" id="p"/>', 0, '<bsdf type="principled" id="p">',
     "the principled BSDF is unsupported (out of scope)"),
    ('<bsdf type="diffuse" id="d">\n<float name="roughness" value="0.1"/>\n</bsdf>', 1,
     '<float name="roughness">', 'unsupported parameter of <bsdf type="diffuse" id="d">'),
    ('<bsdf type="conductor" id="c"><string name="material" value="Unobtainium"/></bsdf>', 0,
     '<string name="material">', "unknown conductor 'Unobtainium'"),
    ('<bsdf type="roughconductor" id="r">\n<string name="distribution" value="phong"/></bsdf>', 1,
     '<string name="distribution">', "distribution 'phong' is unknown (ggx or beckmann)"),
    ('<bsdf type="conductor" id="r">\n<spectrum name="k" value="400:1, 700:2"/></bsdf>', 1,
     '<spectrum name="k">', "a conductor's eta and k as a spectrum list are unsupported"),
    ('<bsdf type="roughplastic" id="r"><string name="distribution" value="ggx"/>\n'
     '<float name="alpha_u" value="0.1"/><float name="alpha_v" value="0.2"/></bsdf>', 0,
     '<bsdf type="roughplastic" id="r">', "anisotropic"),
    ('<bsdf type="roughconductor" id="r">\n<float name="alpha_u" value="0.1"/></bsdf>', 0,
     '<bsdf type="roughconductor" id="r">', "needs alpha_v"),
    ('<shape type="obj">\n<string name="filename" value="missing.obj"/></shape>', 1,
     '<string name="filename">', "file 'missing.obj' not found"),
    ('<foo/>', 0, '<foo>', "unsupported element"),
    ('<shape type="cube" flavour="x"/>', 0, '<shape type="cube">', "unsupported attribute 'flavour'"),
    ('<bsdf type="diffuse" id="t"><texture type="volume" name="reflectance"/></bsdf>', 0,
     '<texture type="volume" name="reflectance">', "unsupported plugin"),
    ('<emitter type="envmap"/>', 0, '<emitter type="envmap">', "missing parameter 'filename'"),
    ('<sensor type="radiancemeter"/>', 0, '<sensor type="radiancemeter">', "unsupported plugin"),
    ('<shape type="sdfgrid"/>', 0, '<shape type="sdfgrid">', "unsupported plugin"),
    ('<shape type="cube">\n  <ref id="nope"/></shape>', 1, '<ref id="nope">', "unknown id 'nope'"),
    ('<bsdf type="diffuse" id="s"><spectrum name="reflectance" filename="x.spd"/></bsdf>', 0,
     '<spectrum name="reflectance" filename="x.spd">', "unsupported attribute 'filename'"),
    ('<bsdf type="diffuse" id="v"><rgb name="reflectance" value="1, 2"/></bsdf>', 0,
     '<rgb name="reflectance">', "expected 1 or 3 numbers"),
    ('<bsdf type="diffuse" id="b"><rgb name="reflectance" value="1.5"/></bsdf>', 0,
     '<bsdf type="diffuse" id="b">', "must lie in [0, 1]"),
    ('<shape type="cube">\n<transform name="to_world"><rotate y="1" angle="ninety"/></transform></shape>', 1,
     "<rotate>", "not a number: 'ninety'"),
    ('<bsdf type="diffuse" id="w"/>\n<bsdf type="diffuse" id="w"/>', 1, '<bsdf type="diffuse" id="w">',
     "duplicate id 'w'"),
    ('<emitter type="area" id="lonely"/>', 0, '<emitter type="area" id="lonely">', "not attached"),
    ('<bsdf type="twosided" id="two"><bsdf type="diffuse"/><bsdf type="diffuse"/></bsdf>', 0,
     '<bsdf type="twosided" id="two">', "exactly one BSDF"),
    ('<include filename="nowhere.xml"/>', 0, '<include filename="nowhere.xml">', "not found"),
    ('<bsdf type="dielectric" id="g"><string name="int_ior" value="unobtainium"/></bsdf>', 0,
     '<string name="int_ior">', "unknown IOR name"),
    ('<integrator type="path"><integer name="samples_per_pass" value="2"/></integrator>', 0,
     '<integer name="samples_per_pass">', "unsupported parameter"),
    ('<shape type="cube"><bsdf type="diffuse"/><bsdf type="diffuse"/></shape>', 0, '<shape type="cube">',
     "more than one <bsdf>"),
    ('<shape type="cube"><sampler type="independent"/></shape>', 0, '<sampler type="independent">',
     'not allowed inside <shape type="cube">'),
    ('<float name="stray" value="1"/>', 0, '<float name="stray">', "unsupported parameter of <scene"),
    ('<shape type="cube"><float name="scale" value="2"/></shape>', 0, '<float name="scale">',
     "unsupported parameter"),
    ('<bsdf type="diffuse" id="k"><rgb name="reflectance" value="1"><foo/></rgb></bsdf>', 0, "<foo>",
     'cannot occur inside <rgb name="reflectance">'),
    ('<shape type="cube">', 1, "", "malformed XML: mismatched tag"),
    ('<sensor type="perspective"/>', 0, '<sensor type="perspective">', "a second sensor"),
    ('<bsdf type="roughplastic" id="p"><string name="distribution" value="phong"/></bsdf>', 0,
     '<string name="distribution">', "distribution 'phong' is unknown"),
    ('<bsdf type="mask" id="p"><float name="opacity" value="2"/><bsdf type="diffuse"/></bsdf>', 0,
     '<bsdf type="mask" id="p">', "opacity must lie in [0, 1]"),
    ('<bsdf type="roughdielectric" id="p"><float name="int_ior" value="1"/>'
     '<float name="ext_ior" value="1"/></bsdf>', 0, '<bsdf type="roughdielectric" id="p">',
     "int_ior and ext_ior must differ"),
]


@pytest.mark.parametrize("snippet,offset,element,message", BAD, ids=[b[3][:30] for b in BAD])
def test_errors_name_file_line_and_element(tmp_path, snippet, offset, element, message):
    path = write(tmp_path, TEMPLATE.format(snippet=snippet))
    with pytest.raises(SceneError) as err:
        load_mitsuba_xml(path)
    text = str(err.value)
    assert "\n" not in text
    assert text.startswith(f"{path}:{SNIPPET_LINE + offset}: {element}"), text
    assert message in text, text


def test_template_itself_loads(tmp_path):
    scene = load_mitsuba_xml(write(tmp_path, TEMPLATE.format(snippet="")))
    assert scene.triangle_count == 2 and scene.materials.names == ["default-black+emitter@scene.xml:8"]


def test_error_inside_an_include_names_the_included_file(tmp_path):
    write(tmp_path, '<scene version="3.0.0">\n\n  <bsdf type="hair"/>\n</scene>\n', name="frag.xml")
    path = write(tmp_path, TEMPLATE.format(snippet='<include filename="frag.xml"/>'))
    with pytest.raises(SceneError, match=r"frag\.xml:3: <bsdf type=\"hair\">: unsupported plugin$"):
        load_mitsuba_xml(path)


def test_mirrored_sensor_and_missing_version_are_refused(tmp_path):
    path = write(tmp_path, TEMPLATE.replace("<lookat", '<scale x="-1"/><lookat').format(snippet=""))
    with pytest.raises(SceneError, match=r"scene\.xml:4: <transform name=\"to_world\">: .*mirrors"):
        load_mitsuba_xml(path)
    path = write(tmp_path, TEMPLATE.replace(' version="3.0.0"', "").format(snippet=""))
    with pytest.raises(SceneError, match=r"scene\.xml:1: <scene>: missing version"):
        load_mitsuba_xml(path)
