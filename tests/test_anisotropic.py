"""Anisotropic and textured roughness of the rough conductor
(kernels.anisotropic) against Mitsuba 3's own roughconductor with
alpha_u != alpha_v: eval, pdf and the sampled direction and weight at the
same random numbers, in its local frame; the density integrates to the
probability that a sample is valid, and the mean weight to the albedo;
alpha_u == alpha_v gives the isotropic kernels' values; the reader; and
the gather, which weighs photons in each hit point's frame."""
import dataclasses

import numpy as np
import pytest

from dosppm_core.kernels import anisotropic as an
from dosppm_core.kernels.materials import B_ANISO, bsdf_rows, eval_colour, pdf_colour
from dosppm_core.kernels.microfacet import sample_visible_aniso, sample_visible_local
from dosppm_core.scene.model import MATERIAL_KINDS, Material, MaterialTable
from tests.helpers.renders import (
    assert_equal_up_to_float_noise,
    floor_and_wall,
    one_triangle_chunk,
    sppm_and_osppm_images,
)

ETA, K = (0.2, 0.9, 1.1), (3.9, 2.4, 2.2)
CASES = {
    "ggx-u-wide": ("ggx", 0.25, 0.05),
    "ggx-v-wide": ("ggx", 0.1, 0.4),
    "beckmann": ("beckmann", 0.3, 0.05),
}


def _row(dist, au, av):
    mat = Material("a", "roughconductor", (1, 1, 1), roughness=au, roughness_v=av, distribution=dist,
                   conductor_eta=ETA, conductor_k=K, specular=(0.9, 0.8, 0.7), two_sided=False)
    return bsdf_rows(MaterialTable.from_materials([mat]))[0]


def _mitsuba_bsdf(mi, dist, au, av):
    return mi.load_dict({
        "type": "roughconductor", "distribution": dist, "alpha_u": au, "alpha_v": av,
        "specular_reflectance": {"type": "rgb", "value": [0.9, 0.8, 0.7]},
        "eta": {"type": "rgb", "value": list(ETA)},
        "k": {"type": "srgb", "color": list(K), "unbounded": True}})


def _si(mi, wo):
    si = mi.SurfaceInteraction3f()
    si.wi = mi.Vector3f(*wo)
    si.sh_frame = mi.Frame3f(mi.Vector3f(0, 0, 1))     # s = x, t = y: alpha_u along x
    return si


def _upper(rng, count):
    for _ in range(count):
        wo, wi = rng.normal(size=3), rng.normal(size=3)
        wo[2], wi[2] = abs(wo[2]), abs(wi[2])
        yield wo / np.linalg.norm(wo), wi / np.linalg.norm(wi)


@pytest.mark.reference
@pytest.mark.parametrize("case", CASES)
def test_eval_pdf_and_samples_match_mitsuba(mi, case):
    dist, au, av = CASES[case]
    row = _row(dist, au, av)
    assert row[B_ANISO] == 1.0
    bsdf = _mitsuba_bsdf(mi, dist, au, av)
    ctx = mi.BSDFContext()
    rng = np.random.default_rng(3)
    seen = 0
    for wo, wi in _upper(rng, 300):
        si = _si(mi, wo)
        ref = np.array(bsdf.eval(ctx, si, mi.Vector3f(*wi)))
        ours = np.array(an.eval_local(row, au, av, *wo, *wi)) * wi[2]
        np.testing.assert_allclose(ours, ref, rtol=2e-3, atol=1e-6)
        assert an.pdf_local(row, au, av, *wo, *wi) == pytest.approx(
            float(bsdf.pdf(ctx, si, mi.Vector3f(*wi))), rel=2e-3, abs=1e-6)
        seen += ref.max() > 1e-3
        u = rng.random(2)
        bs, ref_w = bsdf.sample(ctx, si, 0.5, mi.Point2f(*u))
        ok, i0, i1, i2, f0, f1, f2 = an.sample_local(row, au, av, *wo, *u)
        if ok:
            np.testing.assert_allclose([i0, i1, i2], np.array(bs.wo), atol=2e-3)
            np.testing.assert_allclose([f0, f1, f2], np.array(ref_w), rtol=5e-3, atol=1e-5)
        else:
            assert np.array(ref_w).max() == 0.0
    assert seen > 30


@pytest.mark.parametrize("case", CASES)
def test_density_and_weight_are_consistent(case):
    """The pdf integrates to the fraction of valid samples, and the mean
    sample weight equals the integral of f cos (quadrature over the
    hemisphere): the sampler and eval describe the same lobe."""
    dist, au, av = CASES[case]
    row = _row(dist, au, av)
    rng = np.random.default_rng(5)
    # fine product grid in (cos theta, phi): the lobes are narrow
    nt, nphi = 600, 720
    ct = (np.arange(nt) + 0.5) / nt
    phi = (np.arange(nphi) + 0.5) / nphi * 2 * np.pi
    d_omega = (1.0 / nt) * (2 * np.pi / nphi)
    for wo in ([0.5, 0.3, np.sqrt(1 - 0.34)], [0.0, 0.8, 0.6]):
        pdf_sum, f_sum = 0.0, np.zeros(3)
        for c in ct:
            s = np.sqrt(1 - c * c)
            for p in phi:
                wi = (s * np.cos(p), s * np.sin(p), c)
                pdf_sum += an.pdf_local(row, au, av, *wo, *wi)
                f_sum += np.array(an.eval_local(row, au, av, *wo, *wi)) * c
        pdf_sum *= d_omega
        f_sum *= d_omega
        n = 20000
        ok_count, weight = 0, np.zeros(3)
        for u in rng.random((n, 2)):
            ok, _a, _b, _c, f0, f1, f2 = an.sample_local(row, au, av, *wo, *u)
            ok_count += ok
            weight += (f0, f1, f2)
        assert pdf_sum == pytest.approx(ok_count / n, abs=0.01)
        np.testing.assert_allclose(weight / n, f_sum, rtol=0.02)


def test_equal_alphas_are_the_isotropic_lobe():
    """alpha_u == alpha_v in any frame gives the isotropic kernels' values
    (the rough conductor of `materials`, about its own basis), and the
    visible-normal sampler the same normal bit for bit."""
    rng = np.random.default_rng(9)
    for dist in ("ggx", "beckmann"):
        row = _row(dist, 0.2, 0.2)
        assert row[B_ANISO] == 0.0
        kind = MATERIAL_KINDS["roughconductor"]
        q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
        s, t, n = q[:, 0], q[:, 1], q[:, 2]
        for wo, wi in _upper(rng, 50):
            wo_w, wi_w = q @ wo, q @ wi
            np.testing.assert_allclose(an.eval_world(row, 0.2, 0.2, s, t, n, *wo_w, *wi_w),
                                       eval_colour(kind, row, *n, *wo_w, *wi_w, True), rtol=1e-6, atol=1e-12)
            assert an.pdf_world(row, 0.2, 0.2, s, t, n, *wo_w, *wi_w) == pytest.approx(
                pdf_colour(kind, row, *n, *wo_w, *wi_w), rel=1e-6, abs=1e-12)
            u = rng.random(2)
            d = 1 if dist == "beckmann" else 0
            assert sample_visible_aniso(d, 0.2, 0.2, *wo, *u) == sample_visible_local(d, 0.2, *wo, *u)


# -- the reader and renders ---------------------------------------------------------------
PLANE = """<scene version="3.0.0">
  <integrator type="path"><integer name="max_depth" value="{depth}"/></integrator>
  <sensor type="perspective"><float name="fov" value="30"/>
    <transform name="to_world"><lookat origin="0,-1.5,4" target="0,0,0" up="0,1,0"/></transform>
    <film type="hdrfilm"><integer name="width" value="12"/><integer name="height" value="12"/>
      <rfilter type="box"/></film>
  </sensor>
  <shape type="rectangle"><transform name="to_world"><scale value="2"/></transform>{bsdf}</shape>
  {extra}
  <emitter type="directional"><vector name="direction" value="0.3, -0.6, -1"/>
    <rgb name="irradiance" value="2"/></emitter>
</scene>
"""
CONDUCTOR = ('<bsdf type="roughconductor"><string name="distribution" value="{dist}"/>{alphas}'
             '<rgb name="eta" value="0.2"/><rgb name="k" value="3"/></bsdf>')


def _alphas(au, av):
    return f'<float name="alpha_u" value="{au}"/><float name="alpha_v" value="{av}"/>'


def _constant_textures(au, av):
    return "".join(f'<texture name="{n}" type="checkerboard"><float name="color0" value="{a}"/>'
                   f'<float name="color1" value="{a}"/></texture>' for n, a in (("alpha_u", au), ("alpha_v", av)))


def _scene_file(tmp_path, bsdf, depth=2, extra="", name="plane.xml"):
    path = tmp_path / name
    path.write_text(PLANE.format(bsdf=bsdf, depth=depth, extra=extra))
    return str(path)


def test_reader_maps_the_alphas(tmp_path):
    from dosppm_core.scene.mitsuba import load_mitsuba_xml
    from dosppm_core.scene.model import SceneError

    def material(alphas, dist="ggx"):
        scene = load_mitsuba_xml(_scene_file(tmp_path, CONDUCTOR.format(dist=dist, alphas=alphas)))
        return scene.materials, bsdf_rows(scene.materials)[0]

    iso, iso_row = material('<float name="alpha" value="0.2"/>')
    same, same_row = material(_alphas(0.2, 0.2))
    np.testing.assert_array_equal(iso_row, same_row)        # alpha_u == alpha_v: isotropic, as alpha
    assert same_row[B_ANISO] == 0.0 and same.roughness_v[0] == -1
    mats, row = material(_alphas(0.25, 0.05), "beckmann")
    assert row[B_ANISO] == 1.0 and mats.roughness[0] == 0.25 and mats.roughness_v[0] == pytest.approx(0.05)
    mats, row = material(_constant_textures(0.25, 0.05))
    assert row[B_ANISO] == 1.0 and mats.alpha_u_texture[0] >= 0 and mats.alpha_v_texture[0] >= 0
    with pytest.raises(SceneError, match=r"plane\.xml:\d+: .*not both"):
        material('<float name="alpha" value="0.2"/>' + _alphas(0.2, 0.1))
    with pytest.raises(SceneError, match=r"plane\.xml:\d+: .*needs alpha_v"):
        material('<float name="alpha_u" value="0.2"/>')


def _render(path, iterations=2, seed=1):
    import dosppm_core as dp
    from dosppm_core.scene.mitsuba import load_mitsuba_xml
    return np.asarray(dp.render(load_mitsuba_xml(path), iterations=iterations, mode="sppm", seed=seed))


def test_textured_constant_roughness_renders_as_the_constant(tmp_path):
    """alpha_u and alpha_v from checkerboards of one value render as the
    values given as numbers: the direct light to float rounding, and with
    photons (max_depth 3) nearly so (the texel's luminance differs from the
    number in its last bits, which flips a few Russian roulette choices)."""
    extra = '<shape type="sphere"><point name="center" x="0" y="0.6" z="0.4"/><float name="radius" value="0.3"/></shape>'
    for depth in (2, 3):
        numbers = _render(_scene_file(tmp_path, CONDUCTOR.format(dist="ggx", alphas=_alphas(0.3, 0.08)), depth,
                                      extra, "numbers.xml"))
        textured = _render(_scene_file(tmp_path, CONDUCTOR.format(dist="ggx", alphas=_constant_textures(0.3, 0.08)),
                                       depth, extra, "textured.xml"))
        assert numbers.max() > 0
        close = np.isclose(textured, numbers, rtol=1e-4, atol=1e-6 * numbers.max())
        assert close.all() if depth == 2 else close.mean() > 0.75     # measured 0.83
        assert np.abs(textured - numbers).max() < 5e-3 * numbers.max()  # measured 8e-4
        assert textured.mean() == pytest.approx(numbers.mean(), rel=1e-3)


@pytest.mark.reference
@pytest.mark.parametrize("dist", ["ggx", "beckmann"])
def test_direct_light_off_an_anisotropic_plane_matches_mitsuba(mi, tmp_path, dist):
    """A rectangle (dp/du along x) of alpha_u 0.3, alpha_v 0.05 under a
    directional light: our image within 2% of Mitsuba's on average where
    lit (12% per pixel, its noise), and far from the one with the alphas swapped
    (the frame's s is Mitsuba's, not any tangent)."""
    path = _scene_file(tmp_path, CONDUCTOR.format(dist=dist, alphas=_alphas(0.3, 0.05)))
    ours = _render(path, iterations=256)
    ref = np.asarray(mi.render(mi.load_file(path), spp=1024, seed=1))[..., :3]
    swapped = _render(_scene_file(tmp_path, CONDUCTOR.format(dist=dist, alphas=_alphas(0.05, 0.3)), name="s.xml"),
                      iterations=64)
    lit = ref > 0.05 * ref.max()
    assert lit.sum() > 20
    assert ours[lit].mean() == pytest.approx(ref[lit].mean(), rel=0.02)    # measured -0.2% (beckmann)
    np.testing.assert_allclose(ours[lit], ref[lit], rtol=0.12)             # measured at most 7.4%
    assert np.abs(swapped[lit] - ref[lit]).max() > 0.3 * ref.max()


# A floor of textured anisotropic roughness under a narrow spot, and a wall
# lit only by what the floor's lobe sends it (photons); far off, a
# checkerboard diffuse (texture 0), so the floor's alpha textures (1, 2)
# are renumbered in its chunk.
BOUNCE = floor_and_wall("""<bsdf type="roughconductor"><string name="distribution" value="beckmann"/>
      <texture name="alpha_u" type="checkerboard"><float name="color0" value="0.05"/>
        <float name="color1" value="0.4"/></texture>
      <texture name="alpha_v" type="checkerboard"><float name="color0" value="0.4"/>
        <float name="color1" value="0.1"/></texture></bsdf>""", far=True)


def test_chunked_equals_unchunked_for_a_textured_alpha(tmp_path, chunk_store):
    """The scene above cut by the real subdivider into 2 chunks and
    rendered by OSPPM from the store: the unchunked image up to float
    noise (the chunk carries its alpha textures, renumbered)."""
    from dosppm_core.scene.mitsuba import load_mitsuba_xml
    from dosppm_core.settings import RenderSettings
    path = tmp_path / "bounce.xml"
    path.write_text(BOUNCE)
    scene = load_mitsuba_xml(str(path))
    floor = int(np.flatnonzero(scene.materials.alpha_u_texture >= 0)[0])
    assert (scene.materials.alpha_u_texture[floor], scene.materials.alpha_v_texture[floor]) == (1, 2)
    _chunk, mats, _table = one_triangle_chunk(scene, floor)
    assert (mats.alpha_u_texture[floor], mats.alpha_v_texture[floor]) == (0, 1)
    store = chunk_store(scene, chunks=2)
    assert store.chunk_count == 2
    ref, img = sppm_and_osppm_images(scene, store, RenderSettings(seed=11, photons_per_iteration=30_000), 3)
    wall = np.zeros(ref.shape[:2], bool)
    wall[:12] = True
    assert ref[wall].mean() > 0.01 * ref.mean() > 0     # the wall sees the floor's photons
    assert_equal_up_to_float_noise(img, ref)


@pytest.mark.reference
def test_textured_alphas_are_mitsubas_eval_1(mi, tmp_path):
    """The alphas at a hit equal Mitsuba's eval_1 of the same checkerboards
    at that hit's UV (which, for a checkerboard, is the colour its eval
    does not give: Mitsuba's own quirk, which its references show)."""
    from dosppm_core.scene.mitsuba import load_mitsuba_xml
    textures = "".join(
        f'<texture name="{n}" type="checkerboard"><transform name="to_uv"><scale x="5" y="3"/></transform>'
        f'<float name="color0" value="{a}"/><float name="color1" value="{b}"/></texture>'
        for n, a, b in (("alpha_u", 0.05, 0.3), ("alpha_v", 0.4, 0.1)))
    scene = load_mitsuba_xml(_scene_file(tmp_path, CONDUCTOR.format(dist="ggx", alphas=textures)))
    row = bsdf_rows(scene.materials)[0]
    t = scene.textures
    theirs = [mi.load_dict({"type": "checkerboard", "color0": a, "color1": b,
                            "to_uv": mi.ScalarTransform4f().scale([5, 3, 1])}) for a, b in ((0.05, 0.3), (0.4, 0.1))]
    rng = np.random.default_rng(4)
    for _ in range(300):
        tri = int(rng.integers(len(scene.triangles)))
        u, v = rng.random(2) * 0.5
        uv = (1 - u - v) * scene.uvs[scene.triangles[tri, 0]] + u * scene.uvs[scene.triangles[tri, 1]] + \
            v * scene.uvs[scene.triangles[tri, 2]]
        si = mi.SurfaceInteraction3f()
        si.uv = mi.Point2f(*map(float, uv))
        ours = an.alphas(row, scene.uvs, scene.triangles, t.info, t.uv_map, t.texels, tri, u, v)
        assert ours == pytest.approx([float(x.eval_1(si)) for x in theirs], rel=1e-6)


# -- the gather: photons weighed in each hit point's own frame ---------------------------------
def _frames_case(seed=6, n_hp=40, n_ph=400, au=0.3, av=0.05):
    """Hit points and photons on the floor z = 0 of one anisotropic rough
    conductor, each hit point with its own tangent s about +z (as a
    mesh's dp/du would turn from place to place)."""
    from dosppm_core.jobs import HitPoints, PhotonDeposits
    rng = np.random.default_rng(seed)
    mat = Material("brushed", "roughconductor", (1, 1, 1), roughness=au, roughness_v=av,
                   distribution="ggx", conductor_eta=ETA, conductor_k=K, specular=(0.9, 0.8, 0.7),
                   two_sided=False)
    materials = MaterialTable.from_materials([mat])

    def up(count, min_cos=0.2):
        d = rng.normal(size=(count, 3))
        d[:, 2] = np.abs(d[:, 2]) + min_cos
        return (d / np.linalg.norm(d, axis=1, keepdims=True)).astype(np.float32)

    theta = rng.uniform(0, 2 * np.pi, n_hp)
    frame = np.c_[np.cos(theta), np.sin(theta), np.zeros(n_hp), np.full(n_hp, au), np.full(n_hp, av)]
    hp = HitPoints(position=np.c_[rng.uniform(0, 1, (n_hp, 2)), np.zeros(n_hp)].astype(np.float32), normal=np.tile(np.float32([0, 0, 1]), (n_hp, 1)),
                   outgoing=up(n_hp), weight=rng.uniform(0.2, 1, (n_hp, 3)).astype(np.float32),
                   material=np.zeros(n_hp, np.int32), pixel=np.arange(n_hp, dtype=np.int32),
                   frame=frame.astype(np.float32))
    # Photons on a jittered lattice 0.05 apart: no two share a cell of the
    # finest hash grid, so the hash keeps every one.
    side = int(np.ceil(np.sqrt(n_ph)))
    cells = np.stack(np.meshgrid(np.arange(side), np.arange(side)), -1).reshape(-1, 2)[:n_ph]
    lattice = np.c_[(cells + rng.uniform(0.2, 0.8, (n_ph, 2))) / side, np.zeros(n_ph)]
    ph = PhotonDeposits(position=lattice.astype(np.float32), incoming=up(n_ph),
                        flux=rng.uniform(0.1, 1, (n_ph, 3)).astype(np.float32))
    return hp, ph, np.full(n_hp, 0.2), materials


def _lobe_sums(hp, ph, radius, row):
    """Phi per hit point by brute force: the lobe in each hit point's frame,
    the directions projected on (s, t, n) here in float64."""
    phi = np.zeros((len(hp), 3))
    for h in range(len(hp)):
        n = hp.normal[h].astype(float)
        s = hp.frame[h, :3].astype(float)
        basis = np.stack([s, np.cross(n, s), n])
        wo = basis @ hp.outgoing[h].astype(float)
        au, av = float(hp.frame[h, 3]), float(hp.frame[h, 4])
        d = ph.position - hp.position[h]
        near = np.flatnonzero(np.sum(d * d, axis=1) <= radius[h] ** 2)
        for j in near:
            f = np.array(an.eval_local(row, au, av, *wo, *(basis @ ph.incoming[j].astype(float))))
            phi[h] += f * ph.flux[j] * hp.weight[h]
    return phi


def test_the_gather_weighs_photons_by_each_hit_points_own_lobe():
    """Both gathers' Phi at anisotropic hit points is the brute-force sum
    of each one's lobe in its own frame (`HitPoints.frame`), the lobe
    direct light uses there; without the frames it would be the isotropic
    alpha_u lobe, off by far more than rounding."""
    from dosppm_core.sppm.grid import gather_grid
    from dosppm_core.sppm.hash import build_photon_hash
    hp, ph, radius, materials = _frames_case()
    row = bsdf_rows(materials)[0]
    assert row[B_ANISO] == 1.0
    want = _lobe_sums(hp, ph, radius, row)
    assert (want.sum(axis=1) > 0).mean() > 0.9
    _m, grid = gather_grid(ph, hp, radius, materials, threads=2)
    np.testing.assert_allclose(grid, want, rtol=1e-5, atol=1e-9 * want.max())
    # The hash with one slot per cell and no photon lost keeps every photon.
    table = build_photon_hash(ph, hp.position, radius, 2, resolution=(512, 512, 512), table_size=1 << 27)
    assert table.photons_discarded == 0
    _m, hashed = table.gather(hp, radius, materials, 2)
    np.testing.assert_allclose(hashed, want, rtol=1e-5, atol=1e-9 * want.max())
    isotropic = gather_grid(ph, dataclasses.replace(hp, frame=None), radius, materials, threads=2)[1]
    assert np.abs(isotropic - want).max() > 0.2 * want.max()


def test_photons_light_an_anisotropic_plane_as_direct_light_does(tmp_path, monkeypatch):
    """The anisotropic plane under the directional light, its direct light
    once from photons alone (direct="photons": the gather at each hit
    point) and once by next-event estimation (the lobe in the hit point's
    frame): one image within the photons' noise. With the frames dropped,
    as before hit points carried them, the gather weighs photons by the
    isotropic alpha_u lobe and the test fails."""
    import dosppm_core as dp
    from dosppm_core.scene.mitsuba import load_mitsuba_xml
    from dosppm_core.sppm import grid
    scene = load_mitsuba_xml(_scene_file(tmp_path, CONDUCTOR.format(dist="ggx", alphas=_alphas(0.3, 0.05))))

    def photons_only():
        return np.asarray(dp.render(scene, iterations=24, mode="sppm", seed=3, direct="photons",
                                    photons_per_iteration=200_000))

    nee = np.asarray(dp.render(scene, iterations=24, mode="sppm", seed=3))
    lit = nee > 0.05 * nee.max()
    assert lit.sum() > 20
    photons = photons_only()
    assert photons[lit].mean() == pytest.approx(nee[lit].mean(), rel=0.03)
    np.testing.assert_allclose(photons[lit], nee[lit], rtol=0.2)
    monkeypatch.setattr(grid, "frames_of", lambda hp: None)
    isotropic = photons_only()
    assert abs(isotropic[lit].mean() / nee[lit].mean() - 1) > 0.3      # measured 0.28x


@pytest.mark.parametrize("gather_at", ["server", "tracers"])
def test_the_frames_cross_the_wire_to_either_gather(tmp_path, gather_at):
    """The same plane through the service's messages (`services.inproc`:
    encoded and decoded as over a socket), cut into 2 chunks: the hit
    points arrive with their frames wherever the gather runs, and photons
    alone give the next-event image within noise there too."""
    import dosppm_core as dp
    from dosppm_core.scene.mitsuba import load_mitsuba_xml
    from dosppm_core.settings import RenderSettings
    from services.inproc import InProcessCluster
    from tests.helpers.chunks import MemoryChunks, root_box, uniform_tree
    scene = load_mitsuba_xml(_scene_file(tmp_path, CONDUCTOR.format(dist="ggx", alphas=_alphas(0.3, 0.05))))
    nee = np.asarray(dp.render(scene, iterations=24, mode="sppm", seed=3))
    lit = nee > 0.05 * nee.max()
    provider = MemoryChunks(scene, uniform_tree(root_box(scene), (2, 1, 1)))
    settings = RenderSettings(seed=4, direct="photons", photons_per_iteration=100_000, photon_batch=100_000,
                              photons_per_job=4096, threads=1, max_depth=1)
    c = InProcessCluster(provider, settings, tracers=2, gather_at=gather_at)
    try:
        c.run(photons=2_000_000)
        hits = c.statistics.sppm.stats.hit_points
        assert hits.frame is not None and np.allclose(hits.frame[:, 3:], [0.3, 0.05])
        img = np.asarray(c.image())
    finally:
        c.close()
    assert img[lit].mean() == pytest.approx(nee[lit].mean(), rel=0.04)
