"""Sampling and evaluation of the four materials, one surface point at a time.

Conventions: `n` is the unit geometric normal, `wo` the unit direction back
along the arriving ray (away from the surface), `wi` the sampled direction.
Flux (photons) and importance (eye paths) use the same symmetric BRDFs; only
refraction differs, by the (eta_i/eta_t)^2 radiance scaling on eye paths.
The glossy lobe matches Mitsuba's `roughconductor` (GGX, separable Smith G,
Fresnel 1 for material "none") so references agree.
"""
import math

import numba as nb
import numpy as np

from dosppm_core.scene.model import CONDUCTOR, DIFFUSE, GLASS, GLOSSY, MIRROR

INV_PI = np.float32(1.0 / math.pi)


@nb.njit(cache=True, error_model="numpy")
def dot(a0, a1, a2, b0, b1, b2):
    return a0 * b0 + a1 * b1 + a2 * b2


@nb.njit(cache=True, error_model="numpy")
def basis(n0, n1, n2):
    """Orthonormal tangents of a unit normal (Duff et al. 2017)."""
    s = 1.0 if n2 >= 0.0 else -1.0
    a = -1.0 / (s + n2)
    b = n0 * n1 * a
    return (1.0 + s * n0 * n0 * a, s * b, -s * n0), (b, s + n1 * n1 * a, -n1)


@nb.njit(cache=True, error_model="numpy")
def to_world(x, y, z, n0, n1, n2):
    t, b = basis(n0, n1, n2)
    return (x * t[0] + y * b[0] + z * n0,
            x * t[1] + y * b[1] + z * n1,
            x * t[2] + y * b[2] + z * n2)


@nb.njit(cache=True, error_model="numpy")
def cosine_hemisphere(u1, u2):
    r = math.sqrt(u1)
    phi = 2.0 * math.pi * u2
    return r * math.cos(phi), r * math.sin(phi), math.sqrt(max(0.0, 1.0 - u1))


@nb.njit(cache=True, error_model="numpy")
def fresnel_dielectric(cos_i, eta):
    """Unpolarised Fresnel reflectance; eta = eta_i / eta_t. Returns
    (F, cos_t); F = 1 on total internal reflection."""
    sin2_t = eta * eta * max(0.0, 1.0 - cos_i * cos_i)
    if sin2_t >= 1.0:
        return 1.0, 0.0
    cos_t = math.sqrt(1.0 - sin2_t)
    rs = (eta * cos_i - cos_t) / (eta * cos_i + cos_t)
    rp = (cos_i - eta * cos_t) / (cos_i + eta * cos_t)
    return 0.5 * (rs * rs + rp * rp), cos_t


@nb.njit(cache=True, error_model="numpy")
def ggx_d(cos_h, alpha):
    c2 = cos_h * cos_h
    a2 = alpha * alpha
    d = c2 * (a2 - 1.0) + 1.0
    return a2 / (math.pi * d * d)


@nb.njit(cache=True, error_model="numpy")
def ggx_g1(cos_v, v_dot_h, alpha):
    if cos_v * v_dot_h <= 0.0 or cos_v <= 0.0:
        return 0.0
    tan2 = max(0.0, 1.0 - cos_v * cos_v) / (cos_v * cos_v)
    return 2.0 / (1.0 + math.sqrt(1.0 + alpha * alpha * tan2))


@nb.njit(cache=True, error_model="numpy")
def eval_bsdf(kind, alpha, n0, n1, n2, w0, w1, w2, i0, i1, i2):
    """Scalar factor f of the BRDF (multiply by the material reflectance).
    `n` must face `wo`; zero when `wi` is on the other side (which is the
    side test that keeps photons on the back of a wall out of a hit point)."""
    cos_o = dot(n0, n1, n2, w0, w1, w2)
    cos_i = dot(n0, n1, n2, i0, i1, i2)
    if cos_o <= 0.0 or cos_i <= 0.0:
        return 0.0
    if kind == DIFFUSE:
        return INV_PI
    if kind == GLOSSY:
        h0, h1, h2 = w0 + i0, w1 + i1, w2 + i2
        hl = math.sqrt(h0 * h0 + h1 * h1 + h2 * h2)
        h0, h1, h2 = h0 / hl, h1 / hl, h2 / hl
        cos_h = dot(n0, n1, n2, h0, h1, h2)
        g = ggx_g1(cos_o, dot(w0, w1, w2, h0, h1, h2), alpha) * \
            ggx_g1(cos_i, dot(i0, i1, i2, h0, h1, h2), alpha)
        return ggx_d(cos_h, alpha) * g / (4.0 * cos_o * cos_i)
    return 0.0


@nb.njit(cache=True, error_model="numpy")
def sample_bsdf(kind, two_sided, ior, alpha, n0, n1, n2, w0, w1, w2,
                u1, u2, u3, radiance):
    """Sample a scattered direction.

    Returns (ok, wi0, wi1, wi2, scale, specular): the path weight is
    multiplied by reflectance * scale. `ok` False means absorbed (the black
    back of a one-sided surface, or a glossy sample below the horizon).
    """
    cos_o = dot(n0, n1, n2, w0, w1, w2)
    if kind == GLASS:
        return _sample_glass(ior, n0, n1, n2, w0, w1, w2, cos_o, u1, radiance)
    if cos_o < 0.0:
        if not two_sided:
            return False, 0.0, 0.0, 0.0, 0.0, False
        n0, n1, n2, cos_o = -n0, -n1, -n2, -cos_o
    if kind == DIFFUSE:
        x, y, z = cosine_hemisphere(u1, u2)
        a, b, c = to_world(x, y, z, n0, n1, n2)
        return True, a, b, c, 1.0, False
    if kind == MIRROR:
        k = 2.0 * cos_o
        return True, k * n0 - w0, k * n1 - w1, k * n2 - w2, 1.0, True
    return _sample_glossy(alpha, n0, n1, n2, w0, w1, w2, cos_o, u1, u2)


@nb.njit(cache=True, error_model="numpy")
def glossy_pdf(alpha, n0, n1, n2, w0, w1, w2, i0, i1, i2):
    """Solid-angle density with which `sample_bsdf` picks wi on a glossy
    surface (n facing wo): D(h) cos_h / (4 |wo.h|); zero below the horizon."""
    if dot(n0, n1, n2, i0, i1, i2) <= 0.0 or dot(n0, n1, n2, w0, w1, w2) <= 0.0:
        return 0.0
    h0, h1, h2 = w0 + i0, w1 + i1, w2 + i2
    hl = math.sqrt(h0 * h0 + h1 * h1 + h2 * h2)
    h0, h1, h2 = h0 / hl, h1 / hl, h2 / hl
    wo_h = dot(w0, w1, w2, h0, h1, h2)
    if wo_h <= 0.0:
        return 0.0
    cos_h = dot(n0, n1, n2, h0, h1, h2)
    return ggx_d(cos_h, alpha) * cos_h / (4.0 * wo_h)


@nb.njit(cache=True, error_model="numpy")
def _sample_glossy(alpha, n0, n1, n2, w0, w1, w2, cos_o, u1, u2):
    # Sample h from D(h) cos(theta_h); pdf(wi) = D cos_h / (4 |wo.h|).
    tan2 = alpha * alpha * u1 / max(1.0 - u1, 1e-12)
    cos_h = 1.0 / math.sqrt(1.0 + tan2)
    sin_h = math.sqrt(max(0.0, 1.0 - cos_h * cos_h))
    phi = 2.0 * math.pi * u2
    h0, h1, h2 = to_world(sin_h * math.cos(phi), sin_h * math.sin(phi), cos_h, n0, n1, n2)
    wo_h = dot(w0, w1, w2, h0, h1, h2)
    if wo_h <= 0.0:
        return False, 0.0, 0.0, 0.0, 0.0, False
    i0, i1, i2 = 2.0 * wo_h * h0 - w0, 2.0 * wo_h * h1 - w1, 2.0 * wo_h * h2 - w2
    cos_i = dot(n0, n1, n2, i0, i1, i2)
    if cos_i <= 0.0:
        return False, 0.0, 0.0, 0.0, 0.0, False
    g = ggx_g1(cos_o, wo_h, alpha) * ggx_g1(cos_i, wo_h, alpha)
    # f cos_i / pdf = D G / (4 cos_o cos_i) * cos_i * 4 wo_h / (D cos_h)
    return True, i0, i1, i2, g * wo_h / (cos_o * cos_h), False


@nb.njit(cache=True, error_model="numpy")
def _sample_glass(ior, n0, n1, n2, w0, w1, w2, cos_o, u1, radiance):
    if cos_o >= 0.0:
        eta = 1.0 / ior
    else:
        eta = ior
        n0, n1, n2, cos_o = -n0, -n1, -n2, -cos_o
    f, cos_t = fresnel_dielectric(cos_o, eta)
    if u1 < f:
        k = 2.0 * cos_o
        return True, k * n0 - w0, k * n1 - w1, k * n2 - w2, 1.0, True
    # Refraction: wi = -eta wo + (eta cos_o - cos_t) n.
    k = eta * cos_o - cos_t
    scale = eta * eta if radiance else 1.0
    return True, -eta * w0 + k * n0, -eta * w1 + k * n1, -eta * w2 + k * n2, scale, True


@nb.njit(cache=True, error_model="numpy")
def is_specular(kind):
    """Eye paths pass through these (no hit point); a smooth conductor
    (kernels.materials) is one of them."""
    return kind == MIRROR or kind == GLASS or kind == CONDUCTOR
