"""Anisotropic and textured roughness of the rough conductor
(kernels.anisotropic) against Mitsuba 3's own roughconductor with
alpha_u != alpha_v: eval, pdf and the sampled direction and weight at the
same random numbers, in its local frame; the density integrates to the
probability that a sample is valid, and the mean weight to the albedo;
alpha_u == alpha_v gives the isotropic kernels' values; and the reader."""
import numpy as np
import pytest

from dosppm_core.kernels import anisotropic as an
from dosppm_core.kernels.materials import B_ANISO, bsdf_rows, eval_colour, pdf_colour
from dosppm_core.kernels.microfacet import sample_visible_aniso, sample_visible_local
from dosppm_core.scene.model import MATERIAL_KINDS, Material, MaterialTable

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
