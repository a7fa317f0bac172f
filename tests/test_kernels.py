"""The numba kernels against plain-Python references, chi-square tests of
every sampler, energy conservation per material, and a white furnace of the
whole photon bounce.

Statistics. Every random check runs from a fixed seed, so a run is
deterministic. Thresholds are significance levels, not numbers tuned until
the suite passed: each chi-square test rejects at p < ALPHA and each mean is
compared within Z standard errors, Z the two-sided ALPHA quantile of the
normal. With ALPHA = 1e-4 and about sixty such checks a correct kernel fails
a fresh seed with probability under 1%, while the sample sizes (1e5-1e6)
make a real error in a pdf, a probability or a weight fail by many sigma.
Expected chi-square counts come from integrating the analytic pdf with
Gauss-Legendre quadrature; cells expecting fewer than 5 are pooled, as in
Mitsuba's ChiSquareTest.
"""
import math

import numba as nb
import numpy as np
import pytest
import trimesh

from dosppm_core import trace as tracing
from dosppm_core.accel import Accelerator
from dosppm_core.jobs import ABSORBED, ESCAPED, MAX_DEPTH
from dosppm_core.kernels import bsdf, emit, rng
from dosppm_core.kernels.emit import EMIT_EPS_REL
from dosppm_core.kernels.envmap import env_arrays
from dosppm_core.kernels.paths import ELSEWHERE
from dosppm_core.scene.model import DIFFUSE, GLASS, GLOSSY, MIRROR, Camera, Material, SceneBuilder
from dosppm_core.trace import light_textures
from tests.helpers.renders import leaves

ALPHA = 1e-4
TWO_PI = 2.0 * math.pi


# -- statistics ---------------------------------------------------------------
def _gamma_q(a, x):
    """Regularised upper incomplete gamma Q(a, x) (Numerical Recipes 6.2):
    the series for P below a + 1, Lentz's continued fraction above."""
    if x <= 0.0:
        return 1.0
    log_front = -x + a * math.log(x) - math.lgamma(a)
    if x < a + 1.0:
        term = total = 1.0 / a
        ap = a
        for _ in range(100000):
            ap += 1.0
            term *= x / ap
            total += term
            if abs(term) < abs(total) * 1e-16:
                break
        return max(0.0, 1.0 - total * math.exp(log_front))
    tiny = 1e-300
    b = x + 1.0 - a
    c, d = 1.0 / tiny, 1.0 / b
    h = d
    for i in range(1, 100000):
        an = -i * (i - a)
        b += 2.0
        d = an * d + b
        d = tiny if abs(d) < tiny else d
        c = b + an / c
        c = tiny if abs(c) < tiny else c
        d = 1.0 / d
        h *= d * c
        if abs(d * c - 1.0) < 1e-16:
            break
    return math.exp(log_front) * h


def chi2_sf(stat, dof):
    """P(X > stat) for X chi-square with `dof` degrees of freedom."""
    return _gamma_q(0.5 * dof, 0.5 * stat)


def _normal_quantile(alpha):
    """z with P(|N(0,1)| > z) = alpha, by bisection on erfc."""
    lo, hi = 0.0, 40.0
    for _ in range(200):
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if math.erfc(mid / math.sqrt(2.0)) > alpha else (lo, mid)
    return 0.5 * (lo + hi)


Z = _normal_quantile(ALPHA)


def assert_chi2(observed, expected, what):
    """Pearson's test; cells expecting < 5 are pooled into one cell and a
    cell with exactly zero expectation must stay empty."""
    obs = np.asarray(observed, np.float64).ravel()
    exp = np.asarray(expected, np.float64).ravel()
    assert abs(exp.sum() - obs.sum()) <= 1e-4 * obs.sum(), \
        f"{what}: expected counts integrate to {exp.sum():.1f}, not {obs.sum():.0f}"
    impossible = exp == 0.0
    assert obs[impossible].sum() == 0, f"{what}: {obs[impossible].sum():.0f} samples where pdf = 0"
    small = exp < 5.0
    obs = np.append(obs[~small], obs[small].sum())
    exp = np.append(exp[~small], exp[small].sum())
    if exp[-1] == 0.0:
        obs, exp = obs[:-1], exp[:-1]
    stat = float(np.sum((obs - exp) ** 2 / exp))
    p = chi2_sf(stat, exp.size - 1)
    assert p > ALPHA, f"{what}: chi2 = {stat:.1f} with {exp.size - 1} dof, p = {p:.3g}"


def assert_mean(samples, expected, what):
    """Sample mean within Z standard errors of `expected` (per column)."""
    s = np.asarray(samples, np.float64)
    mean, se = s.mean(axis=0), s.std(axis=0, ddof=1) / math.sqrt(s.shape[0])
    err = np.abs(mean - expected)
    assert np.all(err <= Z * se + 1e-12), f"{what}: mean {mean} vs {expected} (se {se})"


def test_chi2_survival_function_closed_forms():
    for x in (0.1, 1.0, 3.0, 10.0, 40.0):
        assert chi2_sf(x, 2) == pytest.approx(math.exp(-x / 2), rel=1e-12)
        assert chi2_sf(x, 1) == pytest.approx(math.erfc(math.sqrt(x / 2)), rel=1e-10)
        assert chi2_sf(x, 4) == pytest.approx(math.exp(-x / 2) * (1 + x / 2), rel=1e-12)
    # Large dof, both branches (values from scipy.stats.chi2.sf).
    assert chi2_sf(199.0, 199) == pytest.approx(0.48666782597231906, rel=1e-9)
    assert chi2_sf(250.0, 200) == pytest.approx(0.009379131668826098, rel=1e-9)
    assert chi2_sf(150.0, 200) == pytest.approx(0.996647558501813, rel=1e-9)
    assert math.erfc(Z / math.sqrt(2)) == pytest.approx(ALPHA, rel=1e-9)


# -- direction histograms -----------------------------------------------------
def _frame(n, ref=None):
    """Orthonormal (x, y, z = n); x along ref's tangential part if any."""
    z = np.asarray(n, np.float64) / np.linalg.norm(n)
    t = None if ref is None else np.asarray(ref, np.float64) - np.dot(ref, z) * z
    if t is None or np.linalg.norm(t) < 1e-9:
        t = np.cross(z, [1.0, 0.0, 0.0] if abs(z[0]) < 0.9 else [0.0, 1.0, 0.0])
    x = t / np.linalg.norm(t)
    return x, np.cross(z, x), z


def _spherical(dirs, frame):
    x, y, z = frame
    d = np.asarray(dirs, np.float64)
    return d @ z, np.mod(np.arctan2(d @ y, d @ x), TWO_PI)


def _cell_integrals(pdf, cos_edges, phi_edges, order=16):
    """Integral of pdf(cos_theta, phi) over each (cos, phi) cell."""
    x, w = np.polynomial.legendre.leggauss(order)

    def nodes(edges):
        a, b = edges[:-1, None], edges[1:, None]
        return (0.5 * (b - a) * x + 0.5 * (a + b)).ravel(), (0.5 * (b - a) * w).ravel()

    cn, cw = nodes(cos_edges)
    pn, pw = nodes(phi_edges)
    vals = pdf(cn[:, None], pn[None, :]) * cw[:, None] * pw[None, :]
    return vals.reshape(len(cos_edges) - 1, order, len(phi_edges) - 1, order).sum(axis=(1, 3))


def _quantile_edges(pdf, cos_lo, cos_hi, n_cos, n_phi):
    """Bin edges at the quantiles of the pdf's marginals, so that peaked
    lobes are resolved; the edges only define cells, quadrature does the rest."""
    c = np.linspace(cos_lo, cos_hi, 1201)
    p = np.linspace(0.0, TWO_PI, 1441)
    vals = pdf(0.5 * (c[1:] + c[:-1])[:, None], 0.5 * (p[1:] + p[:-1])[None, :])

    def edges(marginal, grid, n):
        cdf = np.concatenate([[0.0], np.cumsum(marginal + 1e-9 * marginal.max())])
        e = np.interp(np.linspace(0.0, 1.0, n + 1), cdf / cdf[-1], grid)
        e[0], e[-1] = grid[0], grid[-1]
        return e

    return edges(vals.sum(1), c, n_cos), edges(vals.sum(0), p, n_phi)


def assert_directions(dirs, frame, pdf, what, cos_lo=0.0, cos_hi=1.0, absorbed=0,
                      absorbed_prob=None, n_cos=10, n_phi=20, adaptive=False):
    """Chi-square test of unit directions against pdf(cos_theta, phi) (per
    steradian) on [cos_lo, cos_hi]; `absorbed` failed samples form one more
    cell expecting `absorbed_prob`, and directions outside the range another
    cell expecting nothing."""
    cos_t, phi = _spherical(dirs, frame)
    n = len(cos_t) + absorbed
    if adaptive:
        ce, pe = _quantile_edges(pdf, cos_lo, cos_hi, n_cos, n_phi)
    else:
        ce, pe = np.linspace(cos_lo, cos_hi, n_cos + 1), np.linspace(0.0, TWO_PI, n_phi + 1)
    slack = 1e-6
    inside = (cos_t >= cos_lo - slack) & (cos_t <= cos_hi + slack)
    obs, _, _ = np.histogram2d(np.clip(cos_t[inside], cos_lo, cos_hi), phi[inside], [ce, pe])
    exp = n * _cell_integrals(pdf, ce, pe)
    if absorbed_prob is None:
        absorbed_prob = 1.0 - exp.sum() / n
    obs = np.append(obs.ravel(), [absorbed, np.count_nonzero(~inside)])
    exp = np.append(exp.ravel(), [n * absorbed_prob, 0.0])
    assert_chi2(obs, exp, what)


def _unit(v):
    v = np.asarray(v, np.float64)
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def _random_directions(gen, count):
    return _unit(gen.normal(size=(count, 3)))


# -- batch wrappers of the scalar kernels ------------------------------------
# Not cached: numba's cache is invalidated only by the defining file, so a
# cached wrapper would keep testing an old bsdf.py after it was edited.
@nb.njit
def _draw_floats(seed, job, first_index, paths, draws):
    out = np.empty((paths, draws), np.float64)
    for i in range(paths):
        st = rng.path_state(np.uint64(seed), np.uint64(job), np.uint64(first_index + i))
        for k in range(draws):
            st, u = rng.next_float(st)
            out[i, k] = u
    return out


@nb.njit
def _sample_many(kind, two_sided, ior, alpha, n, wo, u, radiance):
    """sample_bsdf for rows of n, wo (each (count, 3)) and u (count, 3)."""
    count = u.shape[0]
    ok = np.empty(count, np.bool_)
    wi = np.empty((count, 3), np.float64)
    scale = np.empty(count, np.float64)
    for i in range(count):
        r = bsdf.sample_bsdf(kind, two_sided, ior, alpha, n[i, 0], n[i, 1], n[i, 2],
                             wo[i, 0], wo[i, 1], wo[i, 2], u[i, 0], u[i, 1], u[i, 2], radiance)
        ok[i], wi[i, 0], wi[i, 1], wi[i, 2], scale[i] = r[0], r[1], r[2], r[3], r[4]
    return ok, wi, scale


@nb.njit
def _eval_many(kind, alpha, n, wo, wi):
    out = np.empty(n.shape[0], np.float64)
    for i in range(n.shape[0]):
        out[i] = bsdf.eval_bsdf(kind, alpha, n[i, 0], n[i, 1], n[i, 2], wo[i, 0], wo[i, 1],
                                wo[i, 2], wi[i, 0], wi[i, 1], wi[i, 2])
    return out


@nb.njit
def _fresnel_many(cos_i, eta):
    f = np.empty(cos_i.shape[0], np.float64)
    ct = np.empty(cos_i.shape[0], np.float64)
    for i in range(cos_i.shape[0]):
        f[i], ct[i] = bsdf.fresnel_dielectric(cos_i[i], eta)
    return f, ct


def _sample(kind, n, wo, count, seed, two_sided=True, ior=1.5, alpha=0.1, radiance=False):
    """`count` samples for one (n, wo), uniforms from numpy (independent of
    the generator under test)."""
    u = np.random.default_rng(seed).random((count, 3))
    rows = lambda v: np.ascontiguousarray(np.broadcast_to(np.asarray(v, np.float64), (count, 3)))
    return _sample_many(kind, two_sided, float(ior), float(alpha), rows(n), rows(wo), u, radiance)


# -- 1. the counter-based generator ------------------------------------------
MASK64 = (1 << 64) - 1
GOLDEN = 0x9E3779B97F4A7C15


def _py_mix64(z):
    z = ((z ^ (z >> 30)) * 0xBF58476D1CE4E5B9) & MASK64
    z = ((z ^ (z >> 27)) * 0x94D049BB133111EB) & MASK64
    return z ^ (z >> 31)


def _py_splitmix64(state):
    """One step of Steele et al.'s SplitMix64: (new state, 64-bit output)."""
    state = (state + GOLDEN) & MASK64
    return state, _py_mix64(state)


def _py_path_state(seed, job, index):
    return _py_mix64((_py_mix64(seed ^ _py_mix64((job + GOLDEN) & MASK64)) + index) & MASK64)


def _py_floats(seed, job, index, count):
    st, out = _py_path_state(seed, job, index), []
    for _ in range(count):
        st, z = _py_splitmix64(st)
        out.append((z >> 40) / float(1 << 24))
    return out


def test_python_splitmix64_reproduces_published_sequence():
    # Reference output for seed 1234567 (Vigna's splitmix64.c, as listed on
    # Rosetta Code), anchoring the Python reference used below.
    st, out = 1234567, []
    for _ in range(5):
        st, z = _py_splitmix64(st)
        out.append(z)
    assert out == [6457827717110365317, 3203168211198807973, 9817491932198370423,
                   4593380528125082431, 16408922859458223821]


@pytest.mark.parametrize("seed, job, index", [
    (0, 0, 0), (1, 2, 3), (12345, 7, 1 << 40), (MASK64, MASK64, MASK64),
    (42, int(rng.EYE_STREAM) + 17, 99), (2 ** 63 + 5, 1, 2 ** 32 - 1)])
def test_path_state_and_next_float_match_python_splitmix64(seed, job, index):
    st = rng.path_state(np.uint64(seed), np.uint64(job), np.uint64(index))
    assert int(st) == _py_path_state(seed, job, index)
    ours = []
    for _ in range(16):
        # numba hands a uint64 back as a Python int, which a second call
        # would type as int64 (signed shifts: other numbers); the kernels
        # only ever pass uint64.
        st, u = rng.next_float(np.uint64(st))
        ours.append(float(u))
    assert ours == _py_floats(seed, job, index, 16)
    first = index % (1 << 48)   # path_states takes an int64 first index
    batch = rng.path_states(np.uint64(seed), np.uint64(job), first, 4)
    assert [int(s) for s in batch] == [_py_path_state(seed, job, first + k) for k in range(4)]


def test_next_float_is_uniform_on_24_bit_grid():
    u = _draw_floats(2024, 3, 0, 1 << 17, 8).ravel()
    assert u.min() >= 0.0 and u.max() < 1.0
    assert np.all(u * (1 << 24) == np.floor(u * (1 << 24)))
    n = u.size
    assert abs(u.mean() - 0.5) <= Z * math.sqrt(1 / 12 / n)
    # Var((u - 1/2)^2) = 1/80 - 1/144 = 1/180 for a uniform u.
    assert abs(np.mean((u - 0.5) ** 2) - 1 / 12) <= Z * math.sqrt(1 / 180 / n)
    obs, _ = np.histogram(u, 256, (0.0, 1.0))
    assert_chi2(obs, np.full(256, n / 256), "next_float histogram")
    assert np.unique(rng.path_states(np.uint64(7), np.uint64(0), 0, 1 << 20)).size == 1 << 20


def _assert_independent(a, b, what):
    """2D chi-square of paired uniforms on 16 x 16 cells, plus Pearson r."""
    obs, _, _ = np.histogram2d(a, b, 16, [[0, 1], [0, 1]])
    assert_chi2(obs, np.full((16, 16), a.size / 256), what)
    r = np.corrcoef(a, b)[0, 1]
    assert abs(r) <= Z / math.sqrt(a.size), f"{what}: correlation {r:.4g}"


def test_streams_of_neighbouring_paths_jobs_and_seeds_are_uncorrelated():
    n = 1 << 16
    base = _draw_floats(9, 5, 0, n + 1, 4)
    _assert_independent(base[:-1, 0], base[1:, 0], "adjacent path indices")
    _assert_independent(base[:, 0], base[:, 1], "successive draws of one path")
    _assert_independent(base[:, 2], base[:, 3], "draws 3 and 4 of one path")
    next_job = _draw_floats(9, 6, 0, n + 1, 1)
    _assert_independent(base[:, 0], next_job[:, 0], "adjacent jobs")
    eye = _draw_floats(9, int(rng.EYE_STREAM) + 5, 0, n + 1, 1)
    _assert_independent(base[:, 0], eye[:, 0], "eye stream vs photon job of the same number")
    next_seed = _draw_floats(10, 5, 0, n + 1, 1)
    _assert_independent(base[:, 0], next_seed[:, 0], "adjacent seeds")


# -- Fresnel and BSDF evaluation ---------------------------------------------
def _textbook_fresnel(cos_i, n_i, n_t):
    """Unpolarised Fresnel reflectance from the complex Fresnel equations; a
    complex cos_t makes |r| = 1 under total internal reflection."""
    sin2_t = (n_i / n_t) ** 2 * (1.0 - cos_i ** 2)
    cos_t = np.sqrt(1.0 - sin2_t + 0j)
    rs = (n_i * cos_i - n_t * cos_t) / (n_i * cos_i + n_t * cos_t)
    rp = (n_t * cos_i - n_i * cos_t) / (n_t * cos_i + n_i * cos_t)
    return 0.5 * (abs(rs) ** 2 + abs(rp) ** 2), np.where(sin2_t < 1.0, cos_t.real, 0.0)


@pytest.mark.parametrize("n_i, n_t", [(1.0, 1.5), (1.5, 1.0), (1.0, 2.4), (2.4, 1.0),
                                      (1.33, 1.0), (1.0, 1.0)])
def test_fresnel_dielectric_matches_textbook(n_i, n_t):
    # At grazing incidence on a matched interface (n_i = n_t) F is 0/0.
    cos_i = np.linspace(1e-3 if n_i == n_t else 0.0, 1.0, 2001)
    f, cos_t = _fresnel_many(cos_i, n_i / n_t)
    ref_f, ref_ct = _textbook_fresnel(cos_i, n_i, n_t)
    np.testing.assert_allclose(f, ref_f, rtol=1e-12, atol=1e-14)
    np.testing.assert_allclose(cos_t, ref_ct, rtol=1e-12, atol=1e-14)
    assert f[-1] == pytest.approx(((n_i - n_t) / (n_i + n_t)) ** 2, abs=1e-15)
    if n_i > n_t:   # total internal reflection beyond the critical angle
        tir = np.sqrt(1.0 - cos_i ** 2) > n_t / n_i + 1e-12
        assert np.all(f[tir] == 1.0) and np.all(cos_t[tir] == 0.0)
        assert np.all(f[~tir] < 1.0)
    # Stokes: a refracted pair reflects equally from both sides.
    ok = cos_t > 0.0
    back, _ = _fresnel_many(cos_t[ok], n_t / n_i)
    np.testing.assert_allclose(back, f[ok], rtol=1e-9, atol=1e-12)


def _mitsuba_ggx_d(m, alpha):
    """Mitsuba's MicrofacetDistribution::eval for GGX, isotropic alpha."""
    x, y, z = m[..., 0], m[..., 1], m[..., 2]
    with np.errstate(divide="ignore"):
        d = 1.0 / (math.pi * alpha * alpha * ((x * x + y * y) / alpha ** 2 + z * z) ** 2)
    return np.where(d * z > 1e-20, d, 0.0)


def _mitsuba_smith_g1(v, m, alpha):
    """Mitsuba's MicrofacetDistribution::smith_g1 for GGX."""
    xy_alpha_2 = alpha ** 2 * (v[..., 0] ** 2 + v[..., 1] ** 2)
    result = 2.0 / (1.0 + np.sqrt(1.0 + xy_alpha_2 / v[..., 2] ** 2))
    result = np.where(xy_alpha_2 == 0.0, 1.0, result)
    return np.where(np.sum(v * m, axis=-1) * v[..., 2] <= 0.0, 0.0, result)


def _mitsuba_roughconductor_f(wi, wo, alpha):
    """BRDF f (Mitsuba's eval divided by cos_o) of roughconductor with
    material 'none' (F = 1), in a local frame with the normal along z."""
    cos_i, cos_o = wi[..., 2], wo[..., 2]
    h = _unit(wi + wo)
    with np.errstate(divide="ignore", invalid="ignore"):
        g = _mitsuba_smith_g1(wi, h, alpha) * _mitsuba_smith_g1(wo, h, alpha)
        f = _mitsuba_ggx_d(h, alpha) * g / (4.0 * cos_i * cos_o)
    return np.where((cos_i > 0) & (cos_o > 0), f, 0.0)


def test_eval_bsdf_diffuse_is_one_over_pi_on_the_normal_side():
    gen = np.random.default_rng(1)
    n, wo, wi = (_random_directions(gen, 20000) for _ in range(3))
    f = _eval_many(DIFFUSE, 0.1, n, wo, wi)
    above = (np.sum(n * wo, 1) > 0) & (np.sum(n * wi, 1) > 0)
    np.testing.assert_allclose(f[above], 1 / math.pi, rtol=1e-7)
    assert np.all(f[~above] == 0.0)
    for kind in (MIRROR, GLASS):   # delta lobes have no density
        assert np.all(_eval_many(kind, 0.1, n, wo, wi) == 0.0)


@pytest.mark.parametrize("alpha", [0.02, 0.1, 0.3, 0.7, 1.0])
def test_eval_bsdf_glossy_matches_mitsuba_roughconductor(alpha):
    gen = np.random.default_rng(int(alpha * 1000))
    count = 20000
    n, wo = _random_directions(gen, count), _random_directions(gen, count)
    # Half the wi near the mirror direction, where the lobe is not tiny.
    mirror = 2 * np.sum(n * wo, 1, keepdims=True) * n - wo
    wi = np.where(np.arange(count)[:, None] % 2 == 0, _random_directions(gen, count),
                  _unit(mirror + alpha * gen.normal(size=(count, 3))))
    ours = _eval_many(GLOSSY, alpha, n, wo, wi)
    # Per-row frames with the normal along z (the lobe is isotropic, so any
    # tangent will do).
    x = _unit(np.cross(n, np.where(np.abs(n[:, :1]) < 0.9, [[1.0, 0.0, 0.0]], [[0.0, 1.0, 0.0]])))
    frames = np.stack([x, np.cross(n, x), n], 1)            # (count, 3 axes, 3)
    local = lambda d: np.einsum("iaj,ij->ia", frames, d)
    ref = _mitsuba_roughconductor_f(local(wi), local(wo), alpha)
    np.testing.assert_allclose(ours, ref, rtol=1e-9, atol=1e-12)
    assert np.count_nonzero(ref) > count // 4
    np.testing.assert_allclose(_eval_many(GLOSSY, alpha, n, wi, wo), ours, rtol=1e-12)  # reciprocity


# -- eye rays -----------------------------------------------------------------
def _py_camera(cam):
    """Position, right, up, forward and the half-extent tangents, straight
    from the Camera fields (Mitsuba's perspective conventions)."""
    pos = np.asarray(cam.position, np.float64)
    fwd = _unit(np.subtract(cam.look_at, pos))
    right = _unit(np.cross(fwd, cam.up))
    up = np.cross(right, fwd)
    t = math.tan(math.radians(cam.fov_deg) / 2)
    aspect = cam.width / cam.height
    axis = {"smaller": "x" if aspect <= 1 else "y",
            "larger": "x" if aspect >= 1 else "y"}.get(cam.fov_axis, cam.fov_axis)
    tan_x, tan_y = (t, t / aspect) if axis == "x" else (t * aspect, t)
    return pos, right, up, fwd, tan_x, tan_y


def _pixel_coords(dirs, cam):
    """Continuous (column, row) on the film of pinhole directions."""
    _, right, up, fwd, tan_x, tan_y = _py_camera(cam)
    z = dirs @ fwd
    col = ((dirs @ right) / z / tan_x + 1.0) / 2.0 * cam.width
    row = (1.0 - (dirs @ up) / z / tan_y) / 2.0 * cam.height
    return col, row


def _eye_rays(cam, seed, iteration, start=0, count=None):
    count = cam.width * cam.height if count is None else count
    return emit.generate_eye_rays(cam.frame(), cam.width, np.uint64(seed), np.uint64(iteration),
                                  start, count)


@pytest.mark.parametrize("fov_axis, width, height", [("x", 7, 5), ("y", 7, 5),
                                                     ("smaller", 5, 7), ("larger", 5, 7)])
def test_eye_rays_match_python_pinhole(fov_axis, width, height):
    cam = Camera(position=(0.5, 1.0, 4.0), look_at=(0.2, 0.3, -1.0), up=(0.1, 1.0, 0.0),
                 fov_deg=55.0, width=width, height=height, fov_axis=fov_axis)
    seed, iteration, start = 77, 3, 4
    origin, direction, _ = _eye_rays(cam, seed, iteration, start, 30)
    pos, right, up, fwd, tan_x, tan_y = _py_camera(cam)
    for i, pixel in enumerate(range(start, start + 30)):
        ux, uy = _py_floats(seed, int(rng.EYE_STREAM) + iteration, pixel, 2)
        col, row = pixel % cam.width, pixel // cam.width
        sx = (2 * (col + ux) / cam.width - 1) * tan_x
        sy = (1 - 2 * (row + uy) / cam.height) * tan_y
        np.testing.assert_allclose(direction[i], _unit(fwd + sx * right + sy * up), atol=3e-7)
        np.testing.assert_allclose(origin[i], pos, atol=1e-7)


def test_eye_rays_jitter_uniformly_inside_their_pixel_and_start_on_the_near_plane():
    cam = Camera(position=(0.0, 0.0, 0.0), look_at=(1.0, -0.5, -2.0), up=(0.0, 1.0, 0.0),
                 fov_deg=70.0, width=64, height=48, near_clip=0.25)
    cols, rows = [], []
    for iteration in range(40):
        origin, direction, _ = _eye_rays(cam, 5, iteration)
        col, row = _pixel_coords(direction.astype(np.float64), cam)
        cols.append(col)
        rows.append(row)
        fwd = _py_camera(cam)[3]
        np.testing.assert_allclose(origin @ fwd, 0.25, rtol=1e-5)
        np.testing.assert_allclose(np.cross(origin, direction), 0.0, atol=1e-6)
    pixel = np.tile(np.arange(cam.width * cam.height), 40)
    fx = np.concatenate(cols) - pixel % cam.width
    fy = np.concatenate(rows) - pixel // cam.width
    assert fx.min() > -1e-4 and fx.max() < 1 + 1e-4 and fy.min() > -1e-4 and fy.max() < 1 + 1e-4
    obs, _, _ = np.histogram2d(np.clip(fx, 0, 1), np.clip(fy, 0, 1), 8, [[0, 1], [0, 1]])
    assert_chi2(obs, np.full((8, 8), fx.size / 64), "sub-pixel jitter")


def test_thin_lens_rays_pass_through_the_focus_point_of_their_pixel():
    radius, focus = 0.25, 3.0
    cam = Camera(position=(0.3, -0.2, 1.0), look_at=(0.0, 0.0, -4.0), up=(0.0, 1.0, 0.0),
                 fov_deg=50.0, width=32, height=24, aperture_radius=radius, focus_distance=focus)
    pos, right, up, fwd, _, _ = _py_camera(cam)
    lens, sub = [], []
    for iteration in range(100):
        origin, direction = (a.astype(np.float64) for a in _eye_rays(cam, 11, iteration)[:2])
        rel = origin - pos
        np.testing.assert_allclose(rel @ fwd, 0.0, atol=1e-6)       # on the lens plane
        a, b = rel @ right, rel @ up
        assert np.all(a * a + b * b <= radius ** 2 * (1 + 1e-5))
        # Where the ray meets the focal plane, seen from the lens centre, is
        # the pinhole direction of a point inside the ray's pixel.
        focal = origin + direction * ((focus - rel @ fwd) / (direction @ fwd))[:, None]
        col, row = _pixel_coords(focal - pos, cam)
        pixel = np.arange(cam.width * cam.height)
        sub.append(np.stack([col - pixel % cam.width, row - pixel // cam.width], 1))
        lens.append(np.stack([(a * a + b * b) / radius ** 2, np.arctan2(b, a) % TWO_PI], 1))
    sub, lens = np.concatenate(sub), np.concatenate(lens)
    assert sub.min() > -1e-4 and sub.max() < 1 + 1e-4
    obs, _, _ = np.histogram2d(np.clip(sub[:, 0], 0, 1), np.clip(sub[:, 1], 0, 1), 8,
                               [[0, 1], [0, 1]])
    assert_chi2(obs, np.full((8, 8), len(sub) / 64), "focal-plane jitter")
    # Uniform on the disk: r^2 and the angle are uniform and independent.
    obs, _, _ = np.histogram2d(np.clip(lens[:, 0], 0, 1), lens[:, 1], [10, 20],
                               [[0, 1], [0, TWO_PI]])
    assert_chi2(obs, np.full((10, 20), len(lens) / 200), "lens positions")


# -- photon emission ----------------------------------------------------------
def _light_scene(add_lights):
    b = SceneBuilder(name="lights")
    b.add_material(Material("wall"))
    b.add_mesh([(0, 0, -50), (1, 0, -50), (0, 1, -50)], [(0, 1, 2)], "wall", "test wall")
    add_lights(b)
    b.camera = Camera(position=(0, 0, 5), look_at=(0, 0, 0), up=(0, 1, 0), fov_deg=40,
                      width=4, height=4)
    return b.build()


def _emit(scene, count, seed=3, job=0, eps=1e-4):
    L = scene.lights
    o, d, f, _, _light = emit.emit_photons(L.kind, L.p0, L.p1, L.p2, L.value, L.cone, L.power, L.cdf,
                                           np.uint64(seed), np.array([job], np.uint64),
                                           np.array([0, count], np.int64), eps, env_arrays(L),
                                           light_textures(L))
    return o.astype(np.float64), d.astype(np.float64), f.astype(np.float64)


def _mitsuba_spot_falloff(theta, cutoff, beam):
    return np.where(theta <= beam, 1.0,
                    np.where(theta < cutoff, (cutoff - theta) / (cutoff - beam), 0.0))


def _spot_solid_angle(cutoff, beam, order=64):
    """Integral of the falloff over the sphere, by Gauss-Legendre on both
    pieces of [0, cutoff] (independent of scene._delta_solid_angle)."""
    x, w = np.polynomial.legendre.leggauss(order)
    total = 0.0
    for a, b in ((0.0, beam), (beam, cutoff)):
        t = 0.5 * (b - a) * x + 0.5 * (a + b)
        total += 0.5 * (b - a) * np.sum(w * TWO_PI * np.sin(t) * _mitsuba_spot_falloff(t, cutoff, beam))
    return total


TRIANGLE = np.array([(0.3, -0.2, 0.1), (1.4, 0.5, -0.3), (-0.1, 1.2, 0.6)])
RADIANCE = np.array([2.0, 1.0, 0.5])


def test_triangle_light_photons_leave_its_front_uniformly_with_flux_pi_area_radiance():
    eps = 1e-4
    scene = _light_scene(lambda b: (b.add_material(Material("lamp", emission=tuple(RADIANCE))),
                                    b.add_mesh(TRIANGLE, [(0, 1, 2)], "lamp", "test lamp")))
    count = 200000
    o, d, f = _emit(scene, count, eps=eps)
    a, b, c = TRIANGLE
    cross = np.cross(b - a, c - a)
    area, n = 0.5 * np.linalg.norm(cross), _unit(cross)
    np.testing.assert_allclose(f, np.broadcast_to(math.pi * area * RADIANCE, f.shape), rtol=1e-6)
    # Off the front by eps plus EMIT_EPS_REL * max|p| (relative, so it
    # survives float32 far from the origin), along the normal.
    off = (o - a) @ n
    expected = eps + EMIT_EPS_REL * np.abs(o).max(1)
    assert np.all(np.abs(off - expected) < 1e-6)
    p = o - off[:, None] * n
    # Barycentrics by least squares in the triangle's own edge basis.
    bary = np.linalg.lstsq(np.stack([b - a, c - a], 1), (p - a).T, rcond=None)[0].T
    wa = 1 - bary.sum(1)
    assert np.all(np.concatenate([bary.ravel(), wa]) > -1e-6)
    # Uniform on a triangle: (1 - w_a)^2 and w_b / (1 - w_a) are independent uniforms.
    obs, _, _ = np.histogram2d(np.clip((1 - wa) ** 2, 0, 1),
                               np.clip(bary[:, 0] / np.maximum(1 - wa, 1e-12), 0, 1), 10,
                               [[0, 1], [0, 1]])
    assert_chi2(obs, np.full((10, 10), count / 100), "triangle light origins")
    np.testing.assert_allclose(np.linalg.norm(d, axis=1), 1.0, atol=1e-6)
    assert np.all(d @ n >= 0.0)
    assert_directions(d, _frame(n), lambda ct, ph: ct / math.pi + 0 * ph,
                      "triangle light directions (cosine)")


def test_spot_and_point_light_directions_and_flux():
    cutoff_deg, beam_deg, intensity = 35.0, 20.0, np.array([3.0, 2.0, 1.0])
    pos, target = np.array([0.5, 2.0, -1.0]), np.array([1.0, 0.0, 0.0])
    scene = _light_scene(lambda b: b.add_spot_light(pos, target, intensity, cutoff_deg,
                                                    beam_deg, "test spot"))
    count = 200000
    o, d, f = _emit(scene, count)
    np.testing.assert_allclose(o, np.broadcast_to(pos, o.shape), atol=1e-6)
    axis = _unit(target - pos)
    cos_cut, cutoff, beam = math.cos(math.radians(cutoff_deg)), math.radians(cutoff_deg), \
        math.radians(beam_deg)
    cone = TWO_PI * (1 - cos_cut)
    assert_directions(d, _frame(axis), lambda ct, ph: np.where(ct >= cos_cut, 1 / cone, 0.0) + 0 * ph,
                      "spot directions (uniform in the cone)", cos_lo=cos_cut)
    theta = np.arccos(np.clip(d @ axis, -1, 1))
    expected = intensity * (cone * _mitsuba_spot_falloff(theta, cutoff, beam))[:, None]
    # float32 directions give theta to ~4e-4 rad near the axis, where the
    # falloff is flat, and to ~1e-6 rad in the ramp (slope 1 / (cutoff - beam)).
    np.testing.assert_allclose(f, expected, atol=1e-4 * intensity.max() * cone)
    assert_mean(f, intensity * _spot_solid_angle(cutoff, beam), "spot flux per photon")

    point = _light_scene(lambda b: b.add_point_light(pos, intensity, "test point"))
    o, d, f = _emit(point, count, seed=4)
    np.testing.assert_allclose(f, np.broadcast_to(4 * math.pi * intensity, f.shape), rtol=1e-6)
    assert_directions(d, _frame([0.0, 0.0, 1.0]), lambda ct, ph: 1 / (4 * math.pi) + 0 * ct * ph,
                      "point light directions (uniform sphere)", cos_lo=-1.0)


def test_lights_are_chosen_in_proportion_to_power_and_flux_sums_to_total_power():
    tri_b = np.array([(5.0, 0.0, 0.0), (5.0, 0.0, 1.5), (5.0, 0.8, 0.0)])
    lamp_b = np.float32([0.2, 0.9, 0.4]).astype(np.float64)   # emission is stored as float32
    spot_cone = (30.0, 12.0)

    def add(b):
        b.add_material(Material("lamp_a", emission=tuple(RADIANCE)))
        b.add_material(Material("lamp_b", emission=tuple(lamp_b)))
        b.add_mesh(TRIANGLE, [(0, 1, 2)], "lamp_a", "lamp a")
        b.add_mesh(tri_b, [(0, 1, 2)], "lamp_b", "lamp b")
        b.add_point_light((10, 0, 0), (1.0, 1.0, 1.0), "point 1")
        b.add_point_light((20, 0, 0), (0.3, 0.2, 0.1), "point 2")
        b.add_point_light((30, 0, 0), (0.0, 0.0, 0.0), "dark point")
        b.add_spot_light((40, 0, 0), (40, 0, -1), (4.0, 2.0, 3.0), *spot_cone, "spot")

    scene = _light_scene(add)
    rgb_power = np.array([
        math.pi * 0.5 * np.linalg.norm(np.cross(TRIANGLE[1] - TRIANGLE[0], TRIANGLE[2] - TRIANGLE[0])) * RADIANCE,
        math.pi * 0.5 * np.linalg.norm(np.cross(tri_b[1] - tri_b[0], tri_b[2] - tri_b[0])) * lamp_b,
        4 * math.pi * np.array([1.0, 1.0, 1.0]),
        4 * math.pi * np.array([0.3, 0.2, 0.1]),
        np.zeros(3),
        _spot_solid_angle(*np.radians(spot_cone)) * np.array([4.0, 2.0, 3.0])])
    np.testing.assert_allclose(scene.lights.power, rgb_power.mean(1), rtol=1e-9)
    count = 400000
    o, d, f = _emit(scene, count, seed=8)
    light = np.digitize(o[:, 0], [3.0, 7.5, 15.0, 25.0, 35.0])
    prob = rgb_power.mean(1) / rgb_power.mean(1).sum()
    obs = np.bincount(light, minlength=6)
    assert obs[4] == 0, "a light of zero power emitted photons"
    assert_chi2(obs, count * prob, "light selection")
    for k in (0, 1, 2, 3):   # constant flux per light: radiant power / selection probability
        np.testing.assert_allclose(f[light == k], np.broadcast_to(rgb_power[k] / prob[k], (obs[k], 3)),
                                   rtol=1e-6)
    assert_mean(f, rgb_power.sum(0), "photon flux per channel")
    assert_mean(f.mean(1), scene.lights.total_power, "photon flux (RGB mean)")


# -- 2. chi-square tests of BSDF sampling -------------------------------------
def test_diffuse_sampling_is_cosine_distributed_on_either_side():
    n = _unit([0.3, -0.5, 0.8])
    wo = _unit([0.9, 0.1, 0.2])
    cosine = lambda ct, ph: ct / math.pi + 0 * ph
    ok, wi, scale = _sample(DIFFUSE, n, wo, 200000, seed=21)
    assert ok.all() and np.all(scale == 1.0)
    assert_directions(wi, _frame(n, wo), cosine, "diffuse sampling, front")
    ok, wi, scale = _sample(DIFFUSE, -n, wo, 200000, seed=22, two_sided=True)
    assert ok.all() and np.all(scale == 1.0)
    assert_directions(wi, _frame(n, wo), cosine, "diffuse sampling, back of a two-sided surface")


def _ggx_pdf(theta_o, alpha):
    """pdf(cos_i, phi) of wi per steradian for D(h) cos_h sampling, wo in the
    xz plane: D(h) cos_h / (4 wo.h)."""
    wo = np.array([math.sin(theta_o), 0.0, math.cos(theta_o)])

    def pdf(ct, ph):
        st = np.sqrt(np.maximum(0.0, 1 - ct * ct))
        wi = np.stack(np.broadcast_arrays(st * np.cos(ph), st * np.sin(ph), ct), -1)
        h = _unit(wi + wo)
        return _mitsuba_ggx_d(h, alpha) * h[..., 2] / (4 * (h @ wo))
    return pdf


@pytest.mark.parametrize("alpha", [0.1, 0.5])
@pytest.mark.parametrize("theta_o_deg", [25.0, 70.0])
def test_glossy_sampling_matches_ggx_pdf(alpha, theta_o_deg):
    theta_o = math.radians(theta_o_deg)
    n = _unit([-0.2, 0.4, 0.9])
    frame = _frame(n, [1.0, 0.0, 0.0])
    wo = math.sin(theta_o) * frame[0] + math.cos(theta_o) * frame[2]
    count = 300000
    ok, wi, _ = _sample(GLOSSY, n, wo, count, seed=int(100 * alpha + theta_o_deg), alpha=alpha)
    # Samples with wo.h <= 0 or wi below the horizon are absorbed: the
    # extra cell expects 1 - (integral of the pdf over the hemisphere).
    assert_directions(wi[ok], frame, _ggx_pdf(theta_o, alpha),
                      f"GGX sampling alpha={alpha} theta_o={theta_o_deg}",
                      absorbed=int(np.count_nonzero(~ok)), adaptive=True)


# -- 3. energy ----------------------------------------------------------------
def test_diffuse_and_mirror_scale_is_one_so_mean_weight_is_the_reflectance():
    gen = np.random.default_rng(31)
    for _ in range(20):
        n, wo = _random_directions(gen, 2)
        wo = wo if wo @ n > 0 else -wo
        for kind in (DIFFUSE, MIRROR):
            ok, wi, scale = _sample(kind, n, wo, 1000, seed=32, two_sided=False)
            assert ok.all() and np.all(scale == 1.0)
            np.testing.assert_allclose(np.linalg.norm(wi, axis=1), 1.0, atol=1e-12)
            assert np.all(wi @ n >= 0.0)
            if kind == MIRROR:
                np.testing.assert_allclose(wi, np.broadcast_to(2 * (wo @ n) * n - wo, wi.shape),
                                           atol=1e-12)


@pytest.mark.parametrize("cos_o", [1.0, 0.6, 0.15, -1.0, -0.8, -0.5])
def test_glass_splits_by_fresnel_conserving_flux_and_scaling_radiance_by_eta_squared(cos_o):
    # Photons: every sample survives with scale 1 (weight = tint), so the
    # reflected and transmitted probabilities add up to one and flux is kept;
    # eye paths (radiance) gain (eta_i / eta_t)^2 on refraction.
    ior, count = 1.5, 200000
    n = _unit([0.2, 0.3, -0.9])
    t = _frame(n)[0]
    wo = cos_o * n + math.sqrt(1 - cos_o ** 2) * t
    eta = 1 / ior if cos_o > 0 else ior           # eta_i / eta_t seen from wo
    side = np.sign(cos_o) * n                     # the normal on wo's side
    f_ref, _ = _textbook_fresnel(np.array(abs(cos_o)), 1.0 if cos_o > 0 else ior,
                                 ior if cos_o > 0 else 1.0)
    for radiance in (False, True):
        ok, wi, scale = _sample(GLASS, n, wo, count, seed=41, ior=ior, radiance=radiance)
        assert ok.all(), "glass never absorbs"
        np.testing.assert_allclose(np.linalg.norm(wi, axis=1), 1.0, atol=1e-12)
        refl = wi @ side > 0
        assert abs(refl.mean() - f_ref) <= Z * math.sqrt(f_ref * (1 - f_ref) / count) + 1e-12
        np.testing.assert_allclose(wi[refl], np.broadcast_to(2 * (wo @ side) * side - wo,
                                                              (refl.sum(), 3)), atol=1e-12)
        # Snell: tangential part -eta * wo's, normal part -cos_t.
        wt = wi[~refl]
        np.testing.assert_allclose(wt - np.outer(wt @ side, side),
                                   np.broadcast_to(-eta * (wo - (wo @ side) * side), wt.shape), atol=1e-12)
        assert np.all(scale[refl] == 1.0)
        np.testing.assert_allclose(scale[~refl], eta ** 2 if radiance else 1.0, rtol=1e-12)


def test_glass_total_internal_reflection_reflects_every_sample():
    n = np.array([0.0, 0.0, 1.0])
    wo = _unit([0.9, 0.0, -0.3])                  # inside, beyond the critical angle
    for radiance in (False, True):
        ok, wi, scale = _sample(GLASS, n, wo, 1000, seed=42, radiance=radiance)
        assert ok.all() and np.all(scale == 1.0)
        np.testing.assert_allclose(wi, np.broadcast_to([-wo[0], 0.0, wo[2]], wi.shape), atol=1e-12)


def _glossy_albedo(theta_o, alpha, panels=64, order=8, n_phi=512):
    """Directional albedo: the integral of f cos_i over the hemisphere, by
    composite Gauss-Legendre in theta_i and the periodic trapezoid rule in
    phi, with Mitsuba's roughconductor as f."""
    x, w = np.polynomial.legendre.leggauss(order)
    edges = np.linspace(0.0, math.pi / 2, panels + 1)
    theta = (0.5 * (edges[1:] - edges[:-1])[:, None] * x + 0.5 * (edges[1:] + edges[:-1])[:, None]).ravel()
    w_theta = (0.5 * (edges[1:] - edges[:-1])[:, None] * w).ravel()
    phi = np.arange(n_phi) * TWO_PI / n_phi
    st, ct = np.sin(theta)[:, None], np.cos(theta)[:, None]
    wi = np.stack(np.broadcast_arrays(st * np.cos(phi), st * np.sin(phi), ct), -1)
    wo = np.array([math.sin(theta_o), 0.0, math.cos(theta_o)])
    f = _mitsuba_roughconductor_f(wi, np.broadcast_to(wo, wi.shape), alpha)
    return float(np.sum(f * ct * st * w_theta[:, None]) * TWO_PI / n_phi)


def test_glossy_albedo_quadrature_converged():
    for alpha, theta_o in ((0.1, 0.0), (0.1, 1.3), (1.0, 0.9)):
        a = _glossy_albedo(theta_o, alpha)
        assert a == pytest.approx(_glossy_albedo(theta_o, alpha, 128, 12, 1024), abs=1e-6)
    # Normal incidence, alpha -> 0: a smooth perfect mirror.
    assert _glossy_albedo(0.0, 0.01, 256, 12, 256) == pytest.approx(1.0, abs=2e-3)


@pytest.mark.parametrize("alpha", [0.1, 0.4, 1.0])
@pytest.mark.parametrize("theta_o_deg", [0.0, 50.0, 80.0])
def test_glossy_mean_weight_equals_directional_albedo(alpha, theta_o_deg):
    theta_o = math.radians(theta_o_deg)
    n = _unit([0.5, 0.5, -0.7])
    frame = _frame(n)
    wo = math.sin(theta_o) * frame[0] + math.cos(theta_o) * frame[2]
    ok, wi, scale = _sample(GLOSSY, n, wo, 400000, seed=int(1000 * alpha + theta_o_deg),
                            alpha=alpha)
    weight = np.where(ok, scale, 0.0)
    assert np.all(wi[ok] @ n > 0.0)
    albedo = _glossy_albedo(theta_o, alpha)
    assert albedo <= 1.0
    assert_mean(weight, albedo, f"GGX weight alpha={alpha} theta_o={theta_o_deg}")


@pytest.mark.parametrize("kind", [DIFFUSE, MIRROR, GLOSSY])
def test_one_sided_backs_absorb_and_two_sided_backs_flip(kind):
    gen = np.random.default_rng(51 + kind)
    count = 2000
    n = _unit([0.1, -0.7, 0.4])
    u = gen.random((count, 3))
    rows = lambda v: np.ascontiguousarray(np.broadcast_to(v, (count, 3)))
    for wo in _random_directions(gen, 10):
        wo = wo if wo @ n < 0 else -wo            # on the back
        ok, _, _ = _sample_many(kind, False, 1.5, 0.3, rows(n), rows(wo), u, False)
        assert not ok.any(), "the back of a one-sided surface must be black"
        back = _sample_many(kind, True, 1.5, 0.3, rows(n), rows(wo), u, False)
        front = _sample_many(kind, True, 1.5, 0.3, rows(-n), rows(wo), u, False)
        for a, b in zip(back, front):
            np.testing.assert_array_equal(a, b)
        assert np.all(back[1][back[0]] @ n < 0.0)  # scattered to wo's side
    # eval_bsdf expects n to face wo, and is zero for the other side.
    wo = _random_directions(gen, count)
    wi = _random_directions(gen, count)
    f = _eval_many(kind, 0.3, rows(n), wo, wi)
    assert np.all(f[(wo @ n <= 0) | (wi @ n <= 0)] == 0.0)


# -- 4. white furnace: the whole photon bounce --------------------------------
def _add_ball(builder, kind, radius, centre=(0.0, 0.0, 0.0)):
    """A lossless glass or mirror icosphere, counter-clockwise = outside."""
    ball = trimesh.creation.icosphere(subdivisions=3, radius=radius)
    builder.add_material(Material("ball", kind=kind, reflectance=(1.0, 1.0, 1.0), ior=1.5))
    builder.add_mesh(ball.vertices + np.asarray(centre), ball.faces, "ball", "test ball")


def _furnace(albedo, inward=True, two_sided=True, extra_lights=False, ball=None):
    """A closed icosphere of radius 1 whose every surface has `albedo`,
    lit by a point light (and, optionally, a triangle lamp and a spot),
    optionally holding a lossless glass or mirror ball."""
    sphere = trimesh.creation.icosphere(subdivisions=3, radius=1.0)
    faces = sphere.faces[:, ::-1] if inward else sphere.faces
    b = SceneBuilder(name="furnace")
    b.add_material(Material("wall", reflectance=albedo, two_sided=two_sided))
    b.add_mesh(sphere.vertices, faces, "wall", "test sphere")
    if ball:
        _add_ball(b, ball, 0.35, (0.0, -0.5, 0.1))
    b.add_point_light((0.1, 0.0, 0.0), (1.0, 0.5, 0.25), "test point")
    if extra_lights:
        b.add_material(Material("lamp", reflectance=albedo, emission=(0.5, 2.0, 1.0)))
        b.add_mesh([(-0.2, -0.4, -0.1), (0.3, -0.4, 0.0), (0.0, -0.3, 0.4)], [(0, 1, 2)], "lamp",
                   "test lamp")
        b.add_spot_light((0.0, 0.3, 0.2), (0.5, 1.0, 0.0), (2.0, 1.0, 3.0), 40.0, 25.0, "test spot")
    b.camera = Camera(position=(0, 0, 0), look_at=(0, 0, -1), up=(0, 1, 0), fov_deg=60,
                      width=4, height=4)
    return b.build()


def _trace_furnace(scene, count, max_depth, seed=1):
    surf = tracing.SurfaceData.from_scene(scene)
    accel = Accelerator(scene.vertices, scene.triangles)
    try:
        batch = tracing.emit_photon_job(scene, seed, 0, count, surf.eps_abs)
        deposits, ends, _ = tracing.trace_photons(accel, surf, batch, tracing.NO_CULL, max_depth)
    finally:
        accel.close()
    return batch.weight.astype(np.float64), deposits, ends


def _series_moments(albedo, max_depth):
    """Mean and second moment, per channel, of the deposited flux of one
    unit-flux photon under pbrt's roulette: it survives each bounce with
    probability max(albedo) and its flux is scaled by albedo / max(albedo),
    for at most max_depth deposits."""
    rho = np.asarray(albedo, np.float64)
    keep, r = rho.max(), rho / rho.max()
    ks = np.arange(1, max_depth + 1)
    prob = keep ** (ks - 1) * np.where(ks < max_depth, 1 - keep, 1.0)
    sums = np.cumsum(r[None, :] ** (ks - 1)[:, None], axis=0)   # deposits after k hits
    return prob @ sums, prob @ sums ** 2


@pytest.mark.parametrize("albedo, max_depth, ball", [
    ((0.5, 0.5, 0.5), 64, None), ((0.5, 0.5, 0.5), 3, None), ((0.9, 0.6, 0.3), 50, None),
    ((0.5, 0.5, 0.5), 48, "glass"), ((0.5, 0.5, 0.5), 48, "mirror")])
def test_white_furnace_deposits_the_geometric_series_of_the_albedo(albedo, max_depth, ball):
    scene = _furnace(tuple(np.float32(albedo).tolist()), ball=ball)
    count = 100000
    emitted, deposits, ends = _trace_furnace(scene, count, max_depth)
    assert ends[ESCAPED] == 0, "photons leaked out of a closed sphere"
    rho = np.float32(albedo).astype(np.float64)       # what the kernels multiply by
    # A lossless ball adds specular bounces without deposits or roulette, so
    # the series is that of the diffuse hits alone.
    mean_s, second_s = _series_moments(rho, max_depth)
    phi = 4 * math.pi * np.array([1.0, 0.5, 0.25])
    np.testing.assert_allclose(emitted, np.broadcast_to(phi, emitted.shape), rtol=1e-6)
    total = deposits.flux.astype(np.float64).sum(0) / count
    se = phi * np.sqrt((second_s - mean_s ** 2) / count)
    expected = phi * mean_s       # = phi * sum_k rho^k, k < max_depth
    np.testing.assert_allclose(expected, phi * (1 - rho ** max_depth) / (1 - rho), rtol=1e-12)
    # Photons caught by total internal reflection in the faceted glass ball
    # can reach max_depth; each would have deposited phi * E[S] more on
    # average, so they may lower the total by at most that much.
    trapped = ends[MAX_DEPTH] / count if ball else 0.0
    # Bounded, or a ball that trapped everything would pass the lower bound
    # (measured: 4e-5 of the photons in the glass ball, none in the mirror).
    assert trapped <= 1e-3, f"{trapped:.2%} of the photons trapped at max_depth"
    assert np.all(total - expected <= Z * se) and \
        np.all(expected - total <= Z * se + trapped * expected), f"{total} vs {expected} (se {se})"
    if ball:
        return
    p_last = rho.max() ** (max_depth - 1)             # paths still alive at the last hit
    assert abs(ends[MAX_DEPTH] / count - p_last) <= Z * math.sqrt(p_last * (1 - p_last) / count) + 1e-12


def test_white_furnace_with_triangle_spot_and_point_lights():
    albedo = (0.6, 0.6, 0.6)
    scene = _furnace(albedo, extra_lights=True)
    count, max_depth = 200000, 100
    emitted, deposits, ends = _trace_furnace(scene, count, max_depth, seed=2)
    assert ends[ESCAPED] == 0
    mean_s, second_s = _series_moments(np.float32(albedo).astype(np.float64), max_depth)
    power = np.array([math.pi * 0.5 * np.linalg.norm(np.cross(
        np.subtract((0.3, -0.4, 0.0), (-0.2, -0.4, -0.1)), np.subtract((0.0, -0.3, 0.4), (-0.2, -0.4, -0.1))))
        * np.array([0.5, 2.0, 1.0]), 4 * math.pi * np.array([1.0, 0.5, 0.25]),
        _spot_solid_angle(math.radians(40.0), math.radians(25.0)) * np.array([2.0, 1.0, 3.0])]).sum(0)
    # Photon flux and path length are independent (the albedo is the same
    # everywhere), so E[T] = E[flux] E[S], E[T^2] = E[flux^2] E[S^2].
    total = deposits.flux.astype(np.float64).sum(0) / count
    var = np.mean(emitted ** 2, 0) * second_s - (power * mean_s) ** 2
    expected = power * mean_s
    assert np.all(np.abs(total - expected) <= Z * np.sqrt(var / count)), f"{total} vs {expected}"


@pytest.mark.parametrize("two_sided", [False, True])
def test_furnace_seen_from_the_back_of_its_walls(two_sided):
    scene = _furnace((0.5, 0.5, 0.5), inward=False, two_sided=two_sided)
    count = 50000
    _, deposits, ends = _trace_furnace(scene, count, 64)
    assert ends[ESCAPED] == 0
    if not two_sided:
        assert len(deposits) == 0 and ends.sum() == count, "one-sided backs must absorb"
        return
    mean_s, second_s = _series_moments(np.full(3, 0.5), 64)
    phi = 4 * math.pi * np.array([1.0, 0.5, 0.25])
    total = deposits.flux.astype(np.float64).sum(0) / count
    assert np.all(np.abs(total - phi * mean_s) <= Z * phi * np.sqrt((second_s - mean_s ** 2) / count))
    # The light is inside: every photon stored on a wall's back came from its inner side.
    assert np.all(np.sum(_face_normal_at(scene, deposits.position) * deposits.incoming, 1) < 0)


def _face_normal_at(scene, points):
    """The outward unit normal of the face of the convex, origin-centred
    `scene` that each point lies on: the face whose plane the ray from the
    centre through the point meets first."""
    v = scene.vertices[scene.triangles].astype(np.float64)
    n = _unit(np.cross(v[:, 1] - v[:, 0], v[:, 2] - v[:, 0]))
    offset = np.sum(n * v[:, 0], 1)
    n, offset = n * np.sign(offset)[:, None], np.abs(offset)
    face = np.concatenate([np.argmax(p @ n.T / offset, 1) for p in np.array_split(points, 16)])
    return n[face]


@pytest.mark.parametrize("camera_in_glass", [False, True])
def test_eye_furnace_through_glass_sees_n_squared_radiance_inside(camera_in_glass):
    """In a uniform radiance field L a lossless dielectric holds radiance
    n^2 L: a camera inside a glass ball must see 2.25 L, one outside must
    see L whether or not its rays cross the ball (the eta^2 factors of
    entering and leaving cancel)."""
    radiance = np.array([1.0, 2.0, 3.0])
    sphere = trimesh.creation.icosphere(subdivisions=3, radius=1.0)
    b = SceneBuilder(name="eye furnace")
    b.add_material(Material("sky", reflectance=(0.5, 0.5, 0.5), emission=tuple(radiance)))
    b.add_mesh(sphere.vertices, sphere.faces[:, ::-1], "sky", "test sky")
    _add_ball(b, "glass", 0.4)
    position = (0.0, 0.0, 0.0) if camera_in_glass else (0.05, 0.0, 0.75)
    # One large batch: a few long paths set the number of steps, so many
    # small batches would cost many nearly empty kernel launches.
    b.camera = Camera(position=position, look_at=(0.0, 0.1, -1.0), up=(0, 1, 0), fov_deg=90,
                      width=224, height=224)
    scene = b.build()
    surf = tracing.SurfaceData.from_scene(scene)
    accel = Accelerator(scene.vertices, scene.triangles)
    pixels, max_depth = 224 * 224, 40
    try:
        batch = tracing.eye_ray_job(scene, 13, 0, 0, pixels)
        hits, (pix, rgb), ends = tracing.trace_eye(accel, surf, batch, max_depth)
    finally:
        accel.close()
    assert ends[ESCAPED] == 0
    # Glass reflects all: only roulette past DEEP_DEPTH surfaces (survival
    # capped, the survivors reweighted) or the depth limit end a path early.
    assert len(hits) + ends[MAX_DEPTH] + ends[ABSORBED] == pixels   # the rest end on the sky
    seen = np.zeros((pixels, 3))
    np.add.at(seen, pix, rgb)
    # Roulette past DEEP_DEPTH surfaces ends deep paths and reweights the
    # survivors, so a path reaching max_depth carries more than its share:
    # bound the loss by every path ended early, by the limit or roulette.
    trapped = ends[MAX_DEPTH] + ends[ABSORBED]
    expected = radiance * (2.25 if camera_in_glass else 1.0)
    # Paths entering near grazing meet the inside near the critical angle
    # (F near 1, and beyond it on a faceted ball), and a few per mille
    # never leave; each would have brought `expected` on average.
    lost = trapped / len(seen)
    mean, se = seen.mean(0), seen.std(0, ddof=1) / math.sqrt(len(seen))
    assert np.all(mean - expected <= Z * se) and np.all(expected - mean <= Z * se + lost * expected), \
        f"radiance seen {mean} vs {expected} (se {se})"


def test_photon_bounce_of_a_large_batch_equals_the_bounce_of_each_row_alone():
    """The bounce kernel compacts deposits and survivors in parallel blocks;
    a batch of many blocks must give exactly the rows, in order, that the
    same rows give one at a time (a one-row call is a single block)."""
    scene = _furnace((0.7, 0.5, 0.3), ball="glass")
    surf = tracing.SurfaceData.from_scene(scene)
    accel = Accelerator(scene.vertices, scene.triangles)
    try:
        batch = tracing.emit_photon_job(scene, 3, 0, 20_000, surf.eps_abs)
        batch.job = np.arange(len(batch), dtype=np.int64) // 7
        for _ in range(2):   # a bounce deep, so the depths and fluxes vary
            _, batch, _, _ = tracing.photon_step(accel, surf, batch, tracing.NO_CULL, 10)
        prim, _t, u, v = accel.intersect(batch.origin, batch.direction)
        cull = np.array([[-0.5, -2.0, -2.0], [2.0, 2.0, 2.0]])  # some deposits culled
        dep, nxt, ends, culled = tracing.scatter_photons(surf, batch, prim, u, v, cull, 10)
        rows = [tracing.scatter_photons(surf, batch.slice(i, i + 1), prim[i:i + 1], u[i:i + 1],
                                        v[i:i + 1], cull, 10) for i in range(len(batch))]
    finally:
        accel.close()
    assert len(batch) > 8192 and 0 < culled < len(batch)
    assert culled == sum(r[3] for r in rows)
    np.testing.assert_array_equal(ends, np.sum([r[2] for r in rows], axis=0))
    for got, parts in ((dep, [r[0] for r in rows]), (nxt, [r[1] for r in rows])):
        want = type(got).concat(parts)
        for name, column in got.arrays().items():
            np.testing.assert_array_equal(column, getattr(want, name), err_msg=name)


@pytest.mark.parametrize("kind", ["photon", "eye"])
def test_rows_whose_hit_is_elsewhere_are_skipped_as_if_absent(kind):
    """A ray that left its chunk through a portal keeps its row with prim
    ELSEWHERE: the bounce must give exactly what the batch without those
    rows gives, and count no end for them."""
    scene = _furnace((0.7, 0.5, 0.3), ball="glass")
    surf = tracing.SurfaceData.from_scene(scene)
    accel = Accelerator(scene.vertices, scene.triangles)
    try:
        if kind == "photon":
            batch = tracing.emit_photon_job(scene, 5, 0, 20_000, surf.eps_abs)
        else:
            batch = tracing.eye_ray_job(scene, 5, 0, 0, 20_000)
        prim, _t, u, v = accel.intersect(batch.origin, batch.direction)
    finally:
        accel.close()
    away = np.random.default_rng(1).random(len(batch)) < 0.3
    marked = np.where(away, ELSEWHERE, prim).astype(np.int32)
    kept = np.flatnonzero(~away)
    if kind == "photon":
        got = tracing.scatter_photons(surf, batch, marked, u, v, tracing.NO_CULL, 10)
        want = tracing.scatter_photons(surf, batch.take(kept), prim[kept], u[kept], v[kept],
                                       tracing.NO_CULL, 10)
        records = ((got[0], want[0]), (got[1], want[1]))
        ends = (got[2], want[2])
    else:
        got = tracing.advance_eye(surf, batch, marked, u, v, 10)
        want = tracing.advance_eye(surf, batch.take(kept), prim[kept], u[kept], v[kept], 10)
        records = ((got[0], want[0]), (got[2], want[2]))
        ends = (got[3], want[3])
        np.testing.assert_array_equal(got[1][1], want[1][1])
    np.testing.assert_array_equal(*ends)
    assert ends[0].sum() == len(kept)
    for a, b in records:
        assert len(a) > 0
        for name, column in a.arrays().items():
            np.testing.assert_array_equal(column, getattr(b, name), err_msg=name)


def test_a_materials_tables_flags_are_its_own_when_cached():
    """`SurfaceData`'s flags are computed once per materials table: a plain
    table and a textured, mapped, anisotropic one each get their own,
    asked in turn, and equal to what their arrays say."""
    from dosppm_core.kernels import paths
    from dosppm_core.kernels.materials import B_ANISO, B_NORMAL_MAP
    from tests.helpers.scenes import small_scene

    plain = paths.SurfaceData.from_scene(small_scene("cornell-caustic", 16))
    bsdf, tex = plain.bsdf.copy(), plain.mat_texture.copy()
    bsdf[0, B_ANISO], bsdf[1, B_NORMAL_MAP], tex[2] = 0.3, 0, 0
    other = plain._replace(bsdf=bsdf, mat_texture=tex)
    for _ in range(2):
        assert (plain.textured, plain.anisotropic, plain.shading_mapped) == (False, False, False)
        assert plain.material_extras is None
        assert (other.textured, other.anisotropic, other.shading_mapped) == (True, True, True)
        assert other.material_extras is bsdf


def test_serial_eye_and_direct_kernels_equal_the_parallel_ones():
    """Small batches run the eye bounce and the light sampling on one
    thread (`paths.SERIAL_BELOW`); each gives the parallel kernel's output
    exactly, over a pass with glass and mirror bounces and its long tail of
    light caught in glass; the glossy (MIS) path on a glossy floor."""
    from dosppm_core.kernels import direct, paths
    from dosppm_core.kernels.light_cache import LightCache
    from dosppm_core.trace import EPS_REL, INFINITE, LIGHT_CACHE, SurfaceData, eye_ray_job, light_arrays
    from tests.helpers.scenes import small_scene

    scene = small_scene("cornell-caustic", 48)
    scene.materials.kind[0], scene.materials.roughness[0] = GLOSSY, 0.2      # the white walls
    accel = Accelerator(scene.vertices, scene.triangles, threads=2)
    surf = SurfaceData.from_scene(scene)
    lights = light_arrays(scene.lights, LightCache(scene.bounds(), 1 << 20))
    batch = eye_ray_job(scene, 3, 0, 0, 48 * 48)
    steps = hit_points = 0
    while len(batch):
        prim, _t, u, v = accel.intersect(batch.origin, batch.direction)
        args = ((batch.direction, batch.weight, batch.depth, batch.rng), (prim, u, v), surf,
                surf.smooth_normals, surf.material_extras, 256, EPS_REL)
        a, b = paths.advance_eye_paths(*args), paths.advance_eye_paths_serial(*args)
        for x, y in zip(leaves(a), leaves(b)):
            np.testing.assert_array_equal(x, y)
        ends, _lit, (h, hpos, hn, hmat), (g, no, nd, nw, st) = a
        if len(h):
            hits = (hpos, hn, -batch.direction[h], batch.weight[h], hmat, np.zeros((0, 5)))
            dargs = (hits, np.ascontiguousarray(batch.rng[h]), surf, surf.bsdf,
                     lights[:LIGHT_CACHE], lights[LIGHT_CACHE], lights[INFINITE], True, EPS_REL)
            for x, y in zip(direct.sample_direct(*dargs), direct.sample_direct_serial(*dargs)):
                np.testing.assert_array_equal(x, y)
            # Compiled without the coloured kinds and the infinite lights
            # (None: the scene has neither), the same rays.
            pruned = dargs[:3] + (None,) + dargs[4:6] + (None,) + dargs[7:]
            for x, y in zip(direct.sample_direct(*dargs), direct.sample_direct(*pruned)):
                np.testing.assert_array_equal(x, y)
            hit_points += len(h)
        batch = tracing.RayBatch(no, nd, nw, batch.pixel[g], batch.depth[g] + 1, st, job=batch.job[g])
        steps += 1
    assert steps > 3 and hit_points > 0.9 * 48 * 48

