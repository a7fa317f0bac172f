"""Microfacet distributions and Fresnel terms, as Mitsuba 3 writes them
(include/mitsuba/render/microfacet.h, fresnel.h), so that our rough
dielectric and plastics agree with Mitsuba's references.

Isotropic GGX and Beckmann: D, Smith's separable G1 (Beckmann by Mitsuba's
rational approximation), and sampling of the visible normals (Heitz and
d'Eon 2014, Mitsuba's `sample_visible_11`). Vectors are world-space with
the unit macro normal `n`; the local frame is `bsdf.basis(n)` (any frame
about n will do: the distributions are isotropic). The `_aniso` forms
take local vectors in a frame (s, t, n) that the surface defines
(`kernels.anisotropic`): alpha_u along s, alpha_v along t.

`coating_table` precomputes, per rough plastic, the coating's directional
transmittance and internal reflectance exactly as Mitsuba's roughplastic
does (Gauss-Legendre quadrature over visible-normal samples).
"""
import functools
import math

import numba as nb
import numpy as np

from dosppm_core.kernels.bsdf import basis, dot

GGX, BECKMANN = 0, 1           # indices into scene.model.MICROFACETS
TABLE_RES = 64          # Mitsuba's MI_ROUGH_TRANSMITTANCE_RES
INV_SQRT_PI = 1.0 / math.sqrt(math.pi)


@nb.njit(cache=True, error_model="numpy")
def fresnel(cos_i, eta):
    """Mitsuba's `fresnel`: eta = eta_int / eta_ext, cos_i signed (negative
    from inside). Returns (F, cos_t signed opposite to cos_i, eta_it, eta_ti)."""
    outside = cos_i >= 0.0
    eta_it = eta if outside else 1.0 / eta
    eta_ti = 1.0 / eta if outside else eta
    cos_t2 = 1.0 - (1.0 - cos_i * cos_i) * eta_ti * eta_ti
    ci = abs(cos_i)
    ct = math.sqrt(max(cos_t2, 0.0))
    if eta == 1.0:
        r = 0.0
    elif ci == 0.0:
        r = 1.0
    else:
        a_s = (ci - eta_it * ct) / (ci + eta_it * ct)
        a_p = (ct - eta_it * ci) / (ct + eta_it * ci)
        r = 0.5 * (a_s * a_s + a_p * a_p)
    return r, (-ct if cos_i >= 0.0 else ct), eta_it, eta_ti


def fresnel_diffuse_reflectance(eta: float) -> float:
    """Mitsuba's fit of the hemispherical Fresnel reflectance (fresnel.h)."""
    inv = 1.0 / eta
    if eta < 1.0:
        return 0.0636 * inv + eta * (eta * -1.4399 + 0.7099) + 0.6681
    c = (0.919317, -3.4793, 6.75335, -7.80989, 4.98554, -1.36881)
    return sum(ck * inv ** k for k, ck in enumerate(c))


@nb.njit(cache=True, error_model="numpy")
def distribution_d(dist, alpha, cos_m):
    """D(m) for a microfacet normal at cos_m from the macro normal."""
    c2 = cos_m * cos_m
    a2 = alpha * alpha
    if dist == BECKMANN:
        d = math.exp(-(1.0 - c2) / (a2 * c2)) / (math.pi * a2 * c2 * c2)
    else:
        t = (1.0 - c2) / a2 + c2
        d = 1.0 / (math.pi * a2 * t * t)
    return d if d * cos_m > 1e-20 else 0.0


@nb.njit(cache=True, error_model="numpy")
def smith_g1(dist, alpha, cos_v, v_dot_m):
    """Mitsuba's smith_g1(v, m); zero when v sees the back of m."""
    if v_dot_m * cos_v <= 0.0:
        return 0.0
    xy2 = alpha * alpha * max(0.0, 1.0 - cos_v * cos_v)
    return _g1_from_tan2(dist, xy2 / (cos_v * cos_v))


@nb.njit(cache=True, error_model="numpy")
def _g1_from_tan2(dist, tan2):
    """G1 of a direction whose tan^2 of the angle to the normal, stretched
    by the roughness, is `tan2`: Beckmann's rational fit or GGX's closed form
    (the tail of both `smith_g1` and `smith_g1_aniso`)."""
    if tan2 == 0.0:
        return 1.0
    if dist == BECKMANN:
        a = 1.0 / math.sqrt(tan2)
        if a >= 1.6:
            return 1.0
        return (3.535 * a + 2.181 * a * a) / (1.0 + 2.276 * a + 2.577 * a * a)
    return 2.0 / (1.0 + math.sqrt(1.0 + tan2))


@nb.njit(cache=True, error_model="numpy")
def distribution_d_aniso(dist, alpha_u, alpha_v, x, y, z):
    """Mitsuba's anisotropic D(m), m = (x, y, z) unit in the frame (s, t, n)."""
    c2 = z * z
    a = x / alpha_u
    b = y / alpha_v
    if dist == BECKMANN:
        d = math.exp(-(a * a + b * b) / c2) / (math.pi * alpha_u * alpha_v * c2 * c2)
    else:
        t = a * a + b * b + c2
        d = 1.0 / (math.pi * alpha_u * alpha_v * t * t)
    return d if d * z > 1e-20 else 0.0


@nb.njit(cache=True, error_model="numpy")
def smith_g1_aniso(dist, alpha_u, alpha_v, x, y, z, v_dot_m):
    """Mitsuba's anisotropic smith_g1(v, m), v = (x, y, z) local."""
    if v_dot_m * z <= 0.0:
        return 0.0
    return _g1_from_tan2(dist, ((alpha_u * x) ** 2 + (alpha_v * y) ** 2) / (z * z))


@nb.njit(cache=True, error_model="numpy")
def erfinv(x):
    """Inverse error function (Giles 2010, drjit's single-precision fit)."""
    w = -math.log(max((1.0 - x) * (1.0 + x), 1e-300))
    if w < 5.0:
        w -= 2.5
        p = 2.81022636e-08
        for c in (3.43273939e-07, -3.5233877e-06, -4.39150654e-06, 0.00021858087,
                  -0.00125372503, -0.00417768164, 0.246640727, 1.50140941):
            p = c + p * w
    else:
        w = math.sqrt(w) - 3.0
        p = -0.000200214257
        for c in (0.000100950558, 0.00134934322, -0.00367342844, 0.00573950773,
                  -0.0076224613, 0.00943887047, 1.00167406, 2.83297682):
            p = c + p * w
    return p * x


@nb.njit(cache=True, error_model="numpy")
def _disk_concentric(u1, u2):
    r1, r2 = 2.0 * u1 - 1.0, 2.0 * u2 - 1.0
    if r1 == 0.0 and r2 == 0.0:
        return 0.0, 0.0
    if abs(r1) < abs(r2):
        r, phi = r2, 0.5 * math.pi - 0.25 * math.pi * r1 / r2
    else:
        r, phi = r1, 0.25 * math.pi * r2 / r1
    return r * math.cos(phi), r * math.sin(phi)


@nb.njit(cache=True, error_model="numpy")
def _visible_11(dist, cos_i, u1, u2):
    """Slopes of a visible normal of the alpha = 1 distribution."""
    if dist == BECKMANN:
        tan_i = math.sqrt(max(0.0, 1.0 - cos_i * cos_i)) / cos_i
        cot_i = 1.0 / tan_i if tan_i > 0.0 else math.inf
        maxval = math.erf(cot_i)
        u1 = min(max(u1, 1e-6), 1.0 - 1e-6)
        u2 = min(max(u2, 1e-6), 1.0 - 1e-6)
        x = maxval - (maxval + 1.0) * math.erf(math.sqrt(-math.log(u1)))
        tail = INV_SQRT_PI * tan_i * math.exp(-cot_i * cot_i) if tan_i > 0.0 else 0.0
        u1 *= 1.0 + maxval + tail
        for _ in range(3):
            slope = erfinv(x)
            value = 1.0 + x + INV_SQRT_PI * tan_i * math.exp(-slope * slope) - u1
            x -= value / (1.0 - slope * tan_i)
        return erfinv(x), erfinv(2.0 * u2 - 1.0)
    px, py = _disk_concentric(u1, u2)
    s = 0.5 * (1.0 + cos_i)
    py = math.sqrt(max(0.0, 1.0 - px * px)) * (1.0 - s) + py * s
    pz = math.sqrt(max(0.0, 1.0 - px * px - py * py))
    sin_i = math.sqrt(max(0.0, 1.0 - cos_i * cos_i))
    norm = 1.0 / (sin_i * py + cos_i * pz)
    return (cos_i * py - sin_i * pz) * norm, px * norm


@nb.njit(cache=True, error_model="numpy")
def sample_visible_local(dist, alpha, x, y, z, u1, u2):
    """A microfacet normal visible from local direction (x, y, z), z > 0."""
    return sample_visible_aniso(dist, alpha, alpha, x, y, z, u1, u2)


@nb.njit(cache=True, error_model="numpy")
def sample_visible_aniso(dist, alpha_u, alpha_v, x, y, z, u1, u2):
    """Mitsuba's MicrofacetDistribution::sample with visible normals, in
    the local frame (s, t, n): alpha_u along s, alpha_v along t (equal:
    the isotropic distribution, with the same arithmetic)."""
    sx, sy, sz = alpha_u * x, alpha_v * y, z
    sl = math.sqrt(sx * sx + sy * sy + sz * sz)
    sx, sy, sz = sx / sl, sy / sl, sz / sl
    sin2 = 1.0 - sz * sz
    if sin2 <= 0.0:
        cos_phi, sin_phi = 1.0, 0.0
    else:
        inv = 1.0 / math.sqrt(sin2)
        cos_phi, sin_phi = min(max(sx * inv, -1.0), 1.0), min(max(sy * inv, -1.0), 1.0)
    s0, s1 = _visible_11(dist, sz, u1, u2)
    m0 = (cos_phi * s0 - sin_phi * s1) * alpha_u
    m1 = (sin_phi * s0 + cos_phi * s1) * alpha_v
    ml = math.sqrt(m0 * m0 + m1 * m1 + 1.0)
    return -m0 / ml, -m1 / ml, 1.0 / ml


@nb.njit(cache=True, error_model="numpy")
def sample_visible(dist, alpha, n0, n1, n2, v0, v1, v2, u1, u2):
    """World-space microfacet normal visible from unit v (v.n > 0)."""
    t, b = basis(n0, n1, n2)
    x = dot(t[0], t[1], t[2], v0, v1, v2)
    y = dot(b[0], b[1], b[2], v0, v1, v2)
    z = dot(n0, n1, n2, v0, v1, v2)
    mx, my, mz = sample_visible_local(dist, alpha, x, y, z, u1, u2)
    return (mx * t[0] + my * b[0] + mz * n0, mx * t[1] + my * b[1] + mz * n1,
            mx * t[2] + my * b[2] + mz * n2)


@nb.njit(cache=True, error_model="numpy")
def visible_pdf(dist, alpha, cos_v, cos_m, v_dot_m):
    """Density of `sample_visible`'s m: D(m) G1(v, m) |v.m| / cos_v."""
    return distribution_d(dist, alpha, cos_m) * smith_g1(dist, alpha, cos_v, v_dot_m) * \
        abs(v_dot_m) / cos_v


@nb.njit(cache=True, error_model="numpy")
def _coating_sums(dist, alpha, eta, nodes, weights, out):
    """out[0, k]: transmittance into the coating from cos = mu_k (Mitsuba's
    eval_transmittance); out[1, k]: reflectance from inside (eval_reflectance
    with 1/eta), both by Gauss-Legendre over visible normals."""
    res = out.shape[1]
    for k in range(res):
        mu = max(1e-6, k / (res - 1))
        wx, wz = math.sqrt(1.0 - mu * mu), mu
        for lobe in range(2):
            e = eta if lobe == 0 else 1.0 / eta
            ns, ws = nodes[lobe], weights[lobe]
            acc = 0.0
            for i in range(ns.shape[0]):
                for j in range(ns.shape[0]):
                    mx, my, mz = sample_visible_local(dist, alpha, wx, 0.0, wz,
                                                      0.5 * ns[j] + 0.5, 0.5 * ns[i] + 0.5)
                    c = wx * mx + wz * mz
                    f, cos_t, _eta_it, eta_ti = fresnel(c, e)
                    if lobe == 0:   # refract(wi, m, cos_t, eta_ti)
                        k0 = c * eta_ti + cos_t
                        ox, oy, oz = mx * k0 - wx * eta_ti, my * k0, mz * k0 - wz * eta_ti
                        g = smith_g1(dist, alpha, oz, ox * mx + oy * my + oz * mz) * (1.0 - f)
                        if oz * wz >= 0.0:
                            g = 0.0
                    else:           # reflect(wi, m)
                        ox, oy, oz = 2.0 * c * mx - wx, 2.0 * c * my, 2.0 * c * mz - wz
                        g = smith_g1(dist, alpha, oz, ox * mx + oy * my + oz * mz) * f
                        if oz <= 0.0:
                            g = 0.0
                    acc += g * ws[i] * ws[j] * 0.25
            out[lobe, k] = acc


@functools.lru_cache(maxsize=256)
def coating_table(dist: int, alpha: float, eta: float):
    """(external transmittance at TABLE_RES cosines in [0, 1], internal
    reflectance) of a rough dielectric coating, as roughplastic computes them.
    Cached: every chunk view and gather asks again (~0.1 s each)."""
    rules = []
    for e in (eta, 1.0 / eta):
        x, w = np.polynomial.legendre.leggauss(32 if e > 1 else 128)
        rules.append((x, w))
    res = np.zeros((2, TABLE_RES))
    # numba wants homogeneous tuples: pad both rules to one length with zero weights
    size = max(len(r[0]) for r in rules)
    nodes = np.zeros((2, size))
    weights = np.zeros((2, size))
    for i, (x, w) in enumerate(rules):
        nodes[i, :len(x)], weights[i, :len(w)] = x, w
    _coating_sums(int(dist), max(float(alpha), 1e-4), float(eta), nodes, weights, res)
    mu = np.maximum(1e-6, np.linspace(0.0, 1.0, TABLE_RES))
    res[0].flags.writeable = False
    return res[0], float(np.mean(res[1] * mu) * 2.0)


@nb.njit(cache=True, error_model="numpy")
def lerp_table(table, base, x):
    """Mitsuba's lerp_gather of a TABLE_RES table stored from column `base`."""
    x *= TABLE_RES - 1
    i = min(int(x), TABLE_RES - 2)
    return table[base + i] + (table[base + i + 1] - table[base + i]) * (x - i)
