"""The coloured materials (kernels.materials) against Mitsuba 3's own BSDFs:
eval, pdf and sampling weights over many random directions, in both
transport modes; closed forms (a white furnace for plastic, reciprocity);
and the scene reader's mapping of roughdielectric, plastic, roughplastic,
twosided and mask."""
import numpy as np
import pytest

from dosppm_core.kernels.materials import bsdf_rows, eval_colour, pdf_colour, sample_colour
from dosppm_core.scene.model import MATERIAL_KINDS, Material, MaterialTable

BK7_AIR = 1.5046 / 1.000277

# (our material, Mitsuba's dict): every kind, both distributions, tints, nonlinear.
CASES = {
    "roughplastic-ggx": (
        Material("a", "roughplastic", (0.02, 0.2, 0.1), ior=BK7_AIR, roughness=0.1),
        {"type": "roughplastic", "distribution": "ggx", "alpha": 0.1, "int_ior": "bk7",
         "ext_ior": "air", "diffuse_reflectance": {"type": "rgb", "value": [0.02, 0.2, 0.1]}}),
    "roughplastic-nonlinear-tinted": (
        Material("b", "roughplastic", (0.5, 0.3, 0.8), ior=1.49, roughness=0.4, nonlinear=True,
                 specular=(0.9, 0.7, 0.5)),
        {"type": "roughplastic", "distribution": "ggx", "alpha": 0.4, "int_ior": 1.49, "ext_ior": 1.0,
         "nonlinear": True, "diffuse_reflectance": {"type": "rgb", "value": [0.5, 0.3, 0.8]},
         "specular_reflectance": {"type": "rgb", "value": [0.9, 0.7, 0.5]}}),
    "roughplastic-beckmann": (
        Material("c", "roughplastic", (0.6, 0.6, 0.2), ior=1.49, roughness=0.25, distribution="beckmann"),
        {"type": "roughplastic", "distribution": "beckmann", "alpha": 0.25, "int_ior": 1.49,
         "ext_ior": 1.0, "diffuse_reflectance": {"type": "rgb", "value": [0.6, 0.6, 0.2]}}),
    "plastic": (
        Material("d", "plastic", (0.5, 0.3, 0.8), ior=1.49, nonlinear=True),
        {"type": "plastic", "int_ior": 1.49, "ext_ior": 1.0, "nonlinear": True,
         "diffuse_reflectance": {"type": "rgb", "value": [0.5, 0.3, 0.8]}}),
    "roughdielectric-beckmann": (
        Material("e", "roughdielectric", (1, 1, 1), ior=BK7_AIR, roughness=0.3, distribution="beckmann"),
        {"type": "roughdielectric", "distribution": "beckmann", "alpha": 0.3, "int_ior": "bk7",
         "ext_ior": "air"}),
    "roughdielectric-ggx-tinted": (
        Material("f", "roughdielectric", (0.9, 0.8, 0.7), ior=1.5, roughness=0.2, specular=(0.6, 0.7, 0.8)),
        {"type": "roughdielectric", "distribution": "ggx", "alpha": 0.2, "int_ior": 1.5, "ext_ior": 1.0,
         "specular_transmittance": {"type": "rgb", "value": [0.9, 0.8, 0.7]},
         "specular_reflectance": {"type": "rgb", "value": [0.6, 0.7, 0.8]}}),
    "roughconductor-beckmann": (
        Material("g", "roughconductor", (1, 1, 1), roughness=0.15, distribution="beckmann",
                 conductor_eta=(0.789,) * 3, conductor_k=(6.15,) * 3),
        {"type": "roughconductor", "distribution": "beckmann", "alpha": 0.15,
         "eta": 0.789, "k": 6.15}),
    "roughconductor-ggx-coloured": (
        Material("h", "roughconductor", (1, 1, 1), roughness=0.3, specular=(0.9, 0.8, 0.7),
                 conductor_eta=(0.2, 0.9, 1.1), conductor_k=(3.9, 2.4, 2.2)),
        {"type": "roughconductor", "distribution": "ggx", "alpha": 0.3,
         "specular_reflectance": {"type": "rgb", "value": [0.9, 0.8, 0.7]},
         "eta": {"type": "rgb", "value": [0.2, 0.9, 1.1]},
         "k": {"type": "srgb", "color": [3.9, 2.4, 2.2], "unbounded": True}}),
}


def _row(mat):
    return MATERIAL_KINDS[mat.kind], bsdf_rows(MaterialTable.from_materials([mat]))[0]


def _unit(v):
    return v / np.linalg.norm(v)


def _directions(rng, kind, count):
    """(wo, wi) pairs in the frame z = normal; both sides for a dielectric."""
    for _ in range(count):
        wo, wi = _unit(rng.normal(size=3)), _unit(rng.normal(size=3))
        if kind != MATERIAL_KINDS["roughdielectric"]:   # the others reflect on their front only
            wo[2], wi[2] = abs(wo[2]), abs(wi[2])
        yield wo, wi


def _mitsuba(mi, wo, mode):
    """Mitsuba's surface interaction seen from wo, and its BSDF context."""
    si = mi.SurfaceInteraction3f()
    si.wi = mi.Vector3f(*wo)
    si.sh_frame = mi.Frame3f(mi.Vector3f(0, 0, 1))
    return si, mi.BSDFContext(mode)


@pytest.mark.reference
@pytest.mark.parametrize("case", CASES)
@pytest.mark.parametrize("radiance", [True, False])
def test_eval_and_pdf_match_mitsuba(mi, case, radiance):
    """f |cos| and the sampling density agree with Mitsuba's eval and pdf
    over random directions (a rough dielectric: both sides, reflection and
    transmission; transmission differs between the two modes)."""
    mat, d = CASES[case]
    kind, row = _row(mat)
    mode = mi.TransportMode.Radiance if radiance else mi.TransportMode.Importance
    rng = np.random.default_rng(7)
    bsdf = mi.load_dict(d)
    checked = 0
    for wo, wi in _directions(rng, kind, 400):
        si, ctx = _mitsuba(mi, wo, mode)
        ref = np.array(bsdf.eval(ctx, si, mi.Vector3f(*wi)))
        ref_pdf = float(bsdf.pdf(ctx, si, mi.Vector3f(*wi)))
        ours = np.array(eval_colour(kind, row, 0.0, 0.0, 1.0, *wo, *wi, radiance)) * abs(wi[2])
        pdf = pdf_colour(kind, row, 0.0, 0.0, 1.0, *wo, *wi)
        np.testing.assert_allclose(ours, ref, rtol=2e-3, atol=1e-6)
        assert pdf == pytest.approx(ref_pdf, rel=2e-3, abs=1e-6)
        checked += ref.max() > 1e-3
    assert checked > 50         # the comparison saw real values, not just zeros


def _rotation(n):
    """A rotation taking z to unit n (so world-space kernels see a tilted normal)."""
    z = np.array([0.0, 0.0, 1.0])
    v, c = np.cross(z, n), float(np.dot(z, n))
    k = np.array([[0, -v[2], v[1]], [v[2], 0, -v[0]], [-v[1], v[0], 0]])
    return np.eye(3) + k + k @ k / (1.0 + c)


@pytest.mark.reference
@pytest.mark.parametrize("case", CASES)
@pytest.mark.parametrize("radiance", [True, False])
def test_sampling_weights_match_mitsuba(mi, case, radiance):
    """Each sampled direction's weight (with eta_scale) equals Mitsuba's
    eval / pdf there (a smooth plastic's coating: its F s / q), and the
    mean weight (the albedo) matches Mitsuba's own sampler's, for a tilted
    world normal."""
    mat, d = CASES[case]
    kind, row = _row(mat)
    mode = mi.TransportMode.Radiance if radiance else mi.TransportMode.Importance
    rng = np.random.default_rng(11)
    n = _unit(np.array([0.3, -0.5, 0.8]))
    rot = _rotation(n)
    bsdf = mi.load_dict(d)
    for wo, _ in _directions(rng, kind, 6):
        si, ctx = _mitsuba(mi, wo, mode)
        w = rot @ wo
        ours, theirs = [], []
        for u in rng.random((3000, 3)):
            ok, i0, i1, i2, t0, t1, t2, es, delta = sample_colour(kind, row, *n, *w, *u, radiance)
            weight = np.array([t0, t1, t2]) * es if ok else np.zeros(3)
            ours.append(weight)
            bs, ref_w = bsdf.sample(ctx, si, float(u[0]), mi.Point2f(float(u[1]), float(u[2])))
            theirs.append(np.array(ref_w))
            if ok and not delta:
                wi = rot.T @ np.array([i0, i1, i2])
                ref = np.array(bsdf.eval(ctx, si, mi.Vector3f(*wi))) / float(bsdf.pdf(ctx, si, mi.Vector3f(*wi)))
                np.testing.assert_allclose(weight, ref, rtol=5e-3, atol=1e-5)
        ours, theirs = np.array(ours), np.array(theirs)
        err = 4 * np.sqrt(ours.var(0) / len(ours) + theirs.var(0) / len(theirs)) + 1e-4
        assert np.all(np.abs(ours.mean(0) - theirs.mean(0)) < err), (ours.mean(0), theirs.mean(0))


def _albedo(kind, row, cos_o, rng, count=20000):
    """Mean sample weight (importance transport) seen from cos_o."""
    w = np.array([np.sqrt(1 - cos_o ** 2), 0.0, cos_o])
    total = np.zeros(3)
    for u in rng.random((count, 3)):
        ok, _a, _b, _c, t0, t1, t2, _es, _d = sample_colour(kind, row, 0.0, 0.0, 1.0, *w, *u, False)
        if ok:
            total += (t0, t1, t2)
    return total / count


def test_smooth_plastic_white_furnace():
    """A smooth plastic with a white base reflects, seen from cos_o, its
    coating's F(cos_o) plus (1 - F) of the base light that leaves through
    the coating: (1 - F_ext) / (eta^2 (1 - F_int)), F_ext the coating's
    hemispherical reflectance (integrated here), F_int Mitsuba's fit. A black
    base leaves the coating's F alone."""
    from dosppm_core.kernels.microfacet import fresnel, fresnel_diffuse_reflectance
    eta = 1.49
    mu, wts = np.polynomial.legendre.leggauss(200)
    mu = 0.5 * mu + 0.5
    f_ext = float(np.sum(0.5 * wts * 2 * mu * [fresnel(c, eta)[0] for c in mu]))
    escape = (1 - f_ext) / (eta * eta * (1 - fresnel_diffuse_reflectance(1 / eta)))
    rng = np.random.default_rng(3)
    for base in (1.0, 0.0):
        kind, row = _row(Material("w", "plastic", (base,) * 3, ior=eta))
        for cos_o in (0.95, 0.6, 0.3):
            f = fresnel(cos_o, eta)[0]
            expected = f + (1 - f) * base * escape
            assert _albedo(kind, row, cos_o, rng) == pytest.approx([expected] * 3, rel=0.01), (base, cos_o)


def test_rough_plastic_white_furnace():
    """A white-based rough plastic tends to the smooth plastic as alpha -> 0
    (albedo within 3% at alpha 0.01) and darkens as alpha grows: Mitsuba's
    model loses what the coating's microfacets mask (0.69 at alpha 0.3 seen
    from cos 0.95, as Mitsuba's own sampler measures; test above)."""
    rng = np.random.default_rng(4)
    for cos_o in (0.95, 0.5):
        smooth = _albedo(*_row(Material("s", "plastic", (1.0,) * 3, ior=1.49)), cos_o, rng)
        albedo = [_albedo(*_row(Material("w", "roughplastic", (1.0,) * 3, ior=1.49, roughness=a)),
                          cos_o, rng)[0] for a in (0.01, 0.1, 0.3, 1.0)]
        assert albedo[0] == pytest.approx(smooth[0], rel=0.03)
        assert albedo == sorted(albedo, reverse=True) and albedo[-1] > 0.2


@pytest.mark.parametrize("case", CASES)
def test_reciprocity(case):
    """f(wo, wi) = f(wi, wo) for reflection; a rough dielectric's
    transmission obeys Veach's f(wi -> wo) / eta_o^2 = f(wo -> wi) / eta_i^2
    (eta_x: the index on x's side) in radiance transport, and importance
    transport is its adjoint: f_importance(wi, wo) = f_radiance(wo, wi)."""
    mat, _d = CASES[case]
    kind, row = _row(mat)
    rng = np.random.default_rng(5)
    for wo, wi in _directions(rng, kind, 300):
        a = np.array(eval_colour(kind, row, 0.0, 0.0, 1.0, *wo, *wi, True))
        b = np.array(eval_colour(kind, row, 0.0, 0.0, 1.0, *wi, *wo, True))
        if wo[2] * wi[2] > 0:
            np.testing.assert_allclose(a, b, rtol=1e-6, atol=1e-9)
        else:
            eta_o = mat.ior if wo[2] < 0 else 1.0
            eta_i = mat.ior if wi[2] < 0 else 1.0
            np.testing.assert_allclose(a * eta_i ** 2, b * eta_o ** 2, rtol=1e-5, atol=1e-9)
            imp = np.array(eval_colour(kind, row, 0.0, 0.0, 1.0, *wi, *wo, False))
            np.testing.assert_allclose(a, imp, rtol=1e-5, atol=1e-9)


@pytest.mark.reference
def test_smooth_conductor_weight_matches_mitsuba(mi):
    """A smooth conductor's mirror direction carries its Fresnel of the
    complex index eta + i k per channel, as Mitsuba's conductor samples it."""
    kind, row = _row(Material("c", "conductor", (1, 1, 1), conductor_eta=(0.2, 0.9, 1.1),
                              conductor_k=(3.9, 2.4, 2.2), specular=(0.9, 0.8, 0.7)))
    bsdf = mi.load_dict({"type": "conductor", "eta": {"type": "rgb", "value": [0.2, 0.9, 1.1]},
                         "k": {"type": "srgb", "color": [3.9, 2.4, 2.2], "unbounded": True},
                         "specular_reflectance": {"type": "rgb", "value": [0.9, 0.8, 0.7]}})
    for cos_o in (0.99, 0.7, 0.3, 0.05):
        wo = np.array([np.sqrt(1 - cos_o ** 2), 0.0, cos_o])
        si, ctx = _mitsuba(mi, wo, mi.TransportMode.Radiance)
        _bs, ref = bsdf.sample(ctx, si, 0.5, mi.Point2f(0.5, 0.5))
        ok, i0, i1, i2, t0, t1, t2, _es, delta = sample_colour(kind, row, 0.0, 0.0, 1.0, *wo, 0.5, 0.5, 0.5, True)
        assert ok and delta and np.allclose([i0, i1, i2], [-wo[0], 0.0, cos_o])
        np.testing.assert_allclose([t0, t1, t2], np.array(ref), rtol=1e-4)
