"""The coloured materials: rough dielectric, plastic and rough plastic, and
the opacity of a `mask`, one surface point at a time.

Mitsuba 3's formulas (src/bsdfs/roughdielectric.cpp, plastic.cpp,
roughplastic.cpp), in `bsdf.py`'s conventions: `n` is the unit normal,
`wo` the direction back along the arriving ray (Mitsuba's si.wi), `wi` the
scattered direction (Mitsuba's wo). Eye paths carry radiance, photons
importance; only transmission differs (by eta^2, `radiance`), as for GLASS.
Unlike the four older kinds, these BSDFs are not a scalar times one
reflectance, so `eval_colour` returns the RGB value f (without the cosine).

Each material's parameters are one row of `bsdf_rows` (float64), so a
kernel reads everything with one index: columns B_*.

How SPPM treats them (`holds_hit_points`, `hit_point_eval`):
- roughplastic and roughdielectric hold hit points, as GLOSSY does: the
  gather weights photons by the full BSDF, and direct light uses one-sample
  MIS between the lights and the BSDF (`direct.py`), which is what Mitsuba's
  path tracer does at the same vertex, narrow lobes included. A rough
  dielectric's hit point gathers photons from both sides (its transmission)
  and keeps its geometric normal (the side decides eta). Eye paths do not
  continue through them: that would need a second hit point per path. The
  price is a blurred, noisier view through a nearly smooth rough dielectric
  (alpha ~0.01): its transmitted image comes from the photons at the
  surface. A smooth `dielectric` is the better choice there.
- plastic (smooth) has a delta coating over a diffuse base. An eye path
  chooses a lobe with Mitsuba's sampling probability q(wo): the coating's
  mirror reflection (weight F s / q, the path continues) or the base, where
  it stores a hit point whose BSDF is the base's f / (1 - q), so the
  choice stays unbiased. Photons scatter by the full BSDF.
"""
import math

import numba as nb
import numpy as np

from dosppm_core.kernels.bsdf import INV_PI, cosine_hemisphere, dot, eval_bsdf, to_world
from dosppm_core.kernels.microfacet import (
    TABLE_RES,
    coating_table,
    distribution_d,
    fresnel,
    fresnel_diffuse_reflectance,
    lerp_table,
    sample_visible,
    smith_g1,
    visible_pdf,
)
from dosppm_core.kernels.rng import mix64, next_float
from dosppm_core.kernels.texture import texel_at
from dosppm_core.scene.model import (
    CONDUCTOR,
    DIFFUSE,
    PLASTIC,
    ROUGH_CONDUCTOR,
    ROUGH_DIELECTRIC,
    ROUGH_PLASTIC,
)

# Columns of a material's row in `bsdf_rows`.
B_REFL, B_SPEC, B_ETA, B_ALPHA, B_DIST, B_NONLINEAR = 0, 3, 6, 7, 8, 9
B_SPEC_WEIGHT, B_INTERNAL, B_OPACITY, B_TABLE = 10, 11, 12, 13
B_CETA = B_TABLE + TABLE_RES      # a conductor's complex index: eta (3), then k (3)
B_CK = B_CETA + 3
# Normal and bump maps (`kernels.shading`): texture ids (-1 none), the bump
# scale and the wrappers' option bits.
B_NORMAL_MAP, B_BUMP_MAP, B_BUMP_SCALE, B_SHADING_FLAGS = B_CK + 3, B_CK + 4, B_CK + 5, B_CK + 6
# A mask's textured opacity; a blendbsdf's two materials, weight and
# textured weight; CHOICE 1 when a hit must first choose what scatters
# (`resolve_surface`). Texture and material ids as floats, -1 for none.
B_OPACITY_TEX, B_BLEND_A, B_BLEND_B, B_BLEND_W, B_BLEND_TEX, B_CHOICE = range(B_CK + 7, B_CK + 13)
# A rough conductor's alpha_v (B_ALPHA is alpha_u), the textures of both
# (-1 none), and ANISO 1 when it needs a tangent frame (`kernels.anisotropic`).
B_ALPHA_V, B_ALPHA_TEX_U, B_ALPHA_TEX_V, B_ANISO = range(B_CHOICE + 1, B_CHOICE + 5)
B_COLS = B_ANISO + 1


def bsdf_rows(materials) -> np.ndarray:
    """(m, B_COLS) float64: every material's BSDF parameters, with what
    Mitsuba precomputes (the sampling weight of the coating, the internal
    reflectance, and rough plastic's coating transmittance per cosine)."""
    m = len(materials.kind)
    rows = np.zeros((m, B_COLS))
    rows[:, B_REFL:B_REFL + 3] = materials.reflectance
    rows[:, B_SPEC:B_SPEC + 3] = materials.specular
    rows[:, B_ETA] = materials.ior
    rows[:, B_ALPHA] = np.maximum(materials.roughness, 1e-4)
    rows[:, B_DIST] = materials.distribution
    rows[:, B_NONLINEAR] = materials.nonlinear
    rows[:, B_OPACITY] = materials.opacity
    rows[:, B_CETA:B_CETA + 3] = materials.conductor_eta
    rows[:, B_CK:B_CK + 3] = materials.conductor_k
    rows[:, B_NORMAL_MAP] = materials.normal_map
    rows[:, B_BUMP_MAP] = materials.bump_map
    rows[:, B_BUMP_SCALE] = materials.bump_scale
    rows[:, B_SHADING_FLAGS] = materials.shading_flags
    textured_mask = materials.opacity_texture >= 0
    rows[textured_mask, B_OPACITY] = 0.0      # marks the mask; the texture gives the value
    rows[:, B_OPACITY_TEX] = materials.opacity_texture
    rows[:, B_BLEND_A:B_BLEND_B + 1] = materials.blend
    rows[:, B_BLEND_W] = materials.blend_weight
    rows[:, B_BLEND_TEX] = materials.blend_texture
    rows[:, B_CHOICE] = (rows[:, B_OPACITY] < 1.0) | (materials.blend[:, 1] >= 0)
    alpha_v = np.where(materials.roughness_v >= 0, materials.roughness_v, materials.roughness)
    rows[:, B_ALPHA_V] = np.maximum(alpha_v, 1e-4)
    rows[:, B_ALPHA_TEX_U] = materials.alpha_u_texture
    rows[:, B_ALPHA_TEX_V] = materials.alpha_v_texture
    rows[:, B_ANISO] = (materials.kind == ROUGH_CONDUCTOR) & (
        (rows[:, B_ALPHA_V] != rows[:, B_ALPHA]) | (materials.alpha_u_texture >= 0)
        | (materials.alpha_v_texture >= 0))
    for i in range(m):
        k = int(materials.kind[i])
        if k not in (PLASTIC, ROUGH_PLASTIC):
            continue
        d_mean = float(np.mean(materials.reflectance[i]))
        s_mean = float(np.mean(materials.specular[i]))
        rows[i, B_SPEC_WEIGHT] = s_mean / (d_mean + s_mean) if d_mean + s_mean > 0 else 1.0
        eta = float(materials.ior[i])
        if k == PLASTIC:
            rows[i, B_INTERNAL] = fresnel_diffuse_reflectance(1.0 / eta)
        else:
            table, internal = coating_table(int(materials.distribution[i]), rows[i, B_ALPHA], eta)
            rows[i, B_TABLE:B_TABLE + TABLE_RES] = table
            rows[i, B_INTERNAL] = internal
    return rows


@nb.njit(cache=True, error_model="numpy")
def is_coloured(kind):
    """The kinds this module evaluates (a BSDF not of the form f * reflectance)."""
    return kind >= ROUGH_DIELECTRIC and kind <= ROUGH_CONDUCTOR


@nb.njit(cache=True, error_model="numpy")
def is_transmissive(kind):
    """A hit point of this kind gathers photons from both sides."""
    return kind == ROUGH_DIELECTRIC


# -- the base of a plastic ---------------------------------------------------------
@nb.njit(cache=True, error_model="numpy")
def _base(row, k, internal):
    """Diffuse reflectance of a plastic's base seen through its coating,
    with the internal scattering (nonlinear: coloured by the base)."""
    d = row[B_REFL + k]
    return d / (1.0 - (d * internal if row[B_NONLINEAR] > 0.0 else internal))


@nb.njit(cache=True, error_model="numpy")
def _plastic_probability(row, kind, cos_o):
    """Mitsuba's probability of sampling the coating rather than the base."""
    sw = row[B_SPEC_WEIGHT]
    if kind == PLASTIC:
        f = fresnel(cos_o, row[B_ETA])[0]
    else:
        f = 1.0 - lerp_table(row, B_TABLE, cos_o)
    ps, pd = f * sw, (1.0 - f) * (1.0 - sw)
    return ps / (ps + pd) if ps + pd > 0.0 else 0.0


@nb.njit(cache=True, error_model="numpy")
def plastic_specular_probability(row, n0, n1, n2, w0, w1, w2):
    """The probability q(wo) with which an eye path leaves a smooth plastic
    by its coating's mirror reflection (the rest makes a hit point)."""
    return _plastic_probability(row, PLASTIC, dot(n0, n1, n2, w0, w1, w2))


# -- evaluation ---------------------------------------------------------------------
@nb.njit(cache=True, error_model="numpy")
def eval_colour(kind, row, n0, n1, n2, w0, w1, w2, i0, i1, i2, radiance):
    """The BSDF f(wo, wi) per RGB channel, without the cosine; a smooth
    plastic's delta coating is not part of it. Plastics take `n` facing
    wo (one-sided: zero otherwise), a rough dielectric its geometric normal."""
    cos_o = dot(n0, n1, n2, w0, w1, w2)
    cos_i = dot(n0, n1, n2, i0, i1, i2)
    if kind == ROUGH_DIELECTRIC:
        f = _rough_dielectric(row, cos_o, cos_i, n0, n1, n2, w0, w1, w2, i0, i1, i2, radiance)
        tint = B_SPEC if cos_o * cos_i > 0.0 else B_REFL
        return f * row[tint], f * row[tint + 1], f * row[tint + 2]
    if cos_o <= 0.0 or cos_i <= 0.0 or kind == CONDUCTOR:
        return 0.0, 0.0, 0.0
    if kind == ROUGH_CONDUCTOR:
        return _rough_conductor(row, cos_o, cos_i, n0, n1, n2, w0, w1, w2, i0, i1, i2)
    eta = row[B_ETA]
    scale = INV_PI / (eta * eta)
    spec = 0.0
    if kind == PLASTIC:
        scale *= (1.0 - fresnel(cos_o, eta)[0]) * (1.0 - fresnel(cos_i, eta)[0])
    else:
        scale *= lerp_table(row, B_TABLE, cos_o) * lerp_table(row, B_TABLE, cos_i)
        spec = _coating_lobe(row, cos_o, cos_i, n0, n1, n2, w0, w1, w2, i0, i1, i2)
    internal = row[B_INTERNAL]
    return (spec * row[B_SPEC] + scale * _base(row, 0, internal),
            spec * row[B_SPEC + 1] + scale * _base(row, 1, internal),
            spec * row[B_SPEC + 2] + scale * _base(row, 2, internal))


@nb.njit(cache=True, error_model="numpy")
def fresnel_conductor(cos_i, eta, k):
    """Mitsuba's fresnel_conductor (after Moeller's Optics): the unpolarised
    reflectance of a conductor of complex index eta + i k."""
    c2 = cos_i * cos_i
    s2 = 1.0 - c2
    t1 = eta * eta - k * k - s2
    a2pb2 = math.sqrt(max(0.0, t1 * t1 + 4.0 * k * k * eta * eta))
    a = math.sqrt(max(0.0, 0.5 * (a2pb2 + t1)))
    term1, term2 = a2pb2 + c2, 2.0 * cos_i * a
    r_s = (term1 - term2) / (term1 + term2)
    term3, term4 = a2pb2 * c2 + s2 * s2, term2 * s2
    return 0.5 * (r_s + r_s * (term3 - term4) / (term3 + term4))


@nb.njit(cache=True, error_model="numpy")
def conductor_tint(row, cos_h):
    """F(cos_h) times the specular tint, per channel."""
    return (fresnel_conductor(cos_h, row[B_CETA], row[B_CK]) * row[B_SPEC],
            fresnel_conductor(cos_h, row[B_CETA + 1], row[B_CK + 1]) * row[B_SPEC + 1],
            fresnel_conductor(cos_h, row[B_CETA + 2], row[B_CK + 2]) * row[B_SPEC + 2])


@nb.njit(cache=True, error_model="numpy")
def _rough_conductor(row, cos_o, cos_i, n0, n1, n2, w0, w1, w2, i0, i1, i2):
    """Mitsuba's roughconductor: F(wo.h) D G / (4 cos_o cos_i), tinted."""
    wo_h, k = _microfacet(row, cos_o, cos_i, n0, n1, n2, w0, w1, w2, i0, i1, i2)
    f0, f1, f2 = conductor_tint(row, wo_h)
    return f0 * k, f1 * k, f2 * k


@nb.njit(cache=True, error_model="numpy")
def _coating_lobe(row, cos_o, cos_i, n0, n1, n2, w0, w1, w2, i0, i1, i2):
    """Rough plastic's coating: F D G / (4 cos_o cos_i), uncoloured."""
    wo_h, k = _microfacet(row, cos_o, cos_i, n0, n1, n2, w0, w1, w2, i0, i1, i2)
    return fresnel(wo_h, row[B_ETA])[0] * k


@nb.njit(cache=True, error_model="numpy")
def _microfacet(row, cos_o, cos_i, n0, n1, n2, w0, w1, w2, i0, i1, i2):
    """(wo.h, D G / (4 cos_o cos_i)) of a reflection lobe: what the rough
    conductor and rough plastic's coating share, Fresnel aside."""
    h0, h1, h2 = w0 + i0, w1 + i1, w2 + i2
    hl = math.sqrt(h0 * h0 + h1 * h1 + h2 * h2)
    h0, h1, h2 = h0 / hl, h1 / hl, h2 / hl
    dist, alpha = int(row[B_DIST]), row[B_ALPHA]
    wo_h = dot(w0, w1, w2, h0, h1, h2)
    g = smith_g1(dist, alpha, cos_o, wo_h) * smith_g1(dist, alpha, cos_i, dot(i0, i1, i2, h0, h1, h2))
    return wo_h, distribution_d(dist, alpha, dot(n0, n1, n2, h0, h1, h2)) * g / (4.0 * cos_o * cos_i)


@nb.njit(cache=True, error_model="numpy")
def _half_vector(row, cos_o, cos_i, n0, n1, n2, w0, w1, w2, i0, i1, i2):
    """Walter et al.'s generalised half vector, on n's side, and the
    relative eta seen from wo's side."""
    eta = row[B_ETA] if cos_o > 0.0 else 1.0 / row[B_ETA]
    k = 1.0 if cos_o * cos_i > 0.0 else eta
    h0, h1, h2 = w0 + k * i0, w1 + k * i1, w2 + k * i2
    hl = math.sqrt(h0 * h0 + h1 * h1 + h2 * h2)
    s = 1.0 / hl if dot(n0, n1, n2, h0, h1, h2) >= 0.0 else -1.0 / hl
    return h0 * s, h1 * s, h2 * s, eta


@nb.njit(cache=True, error_model="numpy")
def _rough_dielectric(row, cos_o, cos_i, n0, n1, n2, w0, w1, w2, i0, i1, i2, radiance):
    """Scalar f of the rough dielectric (Walter et al. 2007, Mitsuba's eval
    divided by |cos_i|); radiance transport scales transmission by 1/eta^2."""
    if cos_o == 0.0 or cos_i == 0.0:
        return 0.0
    h0, h1, h2, eta = _half_vector(row, cos_o, cos_i, n0, n1, n2, w0, w1, w2, i0, i1, i2)
    dist, alpha = int(row[B_DIST]), row[B_ALPHA]
    wo_h = dot(w0, w1, w2, h0, h1, h2)
    wi_h = dot(i0, i1, i2, h0, h1, h2)
    d = distribution_d(dist, alpha, dot(n0, n1, n2, h0, h1, h2))
    f = fresnel(wo_h, row[B_ETA])[0]
    g = smith_g1(dist, alpha, cos_o, wo_h) * smith_g1(dist, alpha, cos_i, wi_h)
    if cos_o * cos_i > 0.0:
        return f * d * g / (4.0 * abs(cos_o) * abs(cos_i))
    scale = 1.0 / (eta * eta) if radiance else 1.0
    den = wo_h + eta * wi_h
    return abs(scale * (1.0 - f) * d * g * eta * eta * wo_h * wi_h / (cos_o * den * den)) / abs(cos_i)


# -- sampling densities -------------------------------------------------------------
@nb.njit(cache=True, error_model="numpy")
def pdf_colour(kind, row, n0, n1, n2, w0, w1, w2, i0, i1, i2):
    """Solid-angle density with which `sample_colour` picks wi (Mitsuba's
    pdf; a smooth plastic's: its base only)."""
    cos_o = dot(n0, n1, n2, w0, w1, w2)
    cos_i = dot(n0, n1, n2, i0, i1, i2)
    if kind == ROUGH_DIELECTRIC:
        return _rough_dielectric_pdf(row, cos_o, cos_i, n0, n1, n2, w0, w1, w2, i0, i1, i2)
    if cos_o <= 0.0 or cos_i <= 0.0 or kind == CONDUCTOR:
        return 0.0
    if kind == ROUGH_CONDUCTOR:
        h0, h1, h2 = w0 + i0, w1 + i1, w2 + i2
        hl = math.sqrt(h0 * h0 + h1 * h1 + h2 * h2)
        wo_h = dot(w0, w1, w2, h0, h1, h2) / hl
        if wo_h <= 0.0:
            return 0.0
        return visible_pdf(int(row[B_DIST]), row[B_ALPHA], cos_o, dot(n0, n1, n2, h0, h1, h2) / hl,
                           wo_h) * cos_o / (4.0 * cos_o * wo_h)
    q = _plastic_probability(row, kind, cos_o)
    p = (1.0 - q) * cos_i * INV_PI
    if kind == ROUGH_PLASTIC:
        h0, h1, h2 = w0 + i0, w1 + i1, w2 + i2
        hl = math.sqrt(h0 * h0 + h1 * h1 + h2 * h2)
        h0, h1, h2 = h0 / hl, h1 / hl, h2 / hl
        dist, alpha = int(row[B_DIST]), row[B_ALPHA]
        wo_h = dot(w0, w1, w2, h0, h1, h2)
        p += q * distribution_d(dist, alpha, dot(n0, n1, n2, h0, h1, h2)) * \
            smith_g1(dist, alpha, cos_o, wo_h) / (4.0 * cos_o)
    return p


@nb.njit(cache=True, error_model="numpy")
def _rough_dielectric_pdf(row, cos_o, cos_i, n0, n1, n2, w0, w1, w2, i0, i1, i2):
    if cos_o == 0.0 or cos_i == 0.0:
        return 0.0
    h0, h1, h2, eta = _half_vector(row, cos_o, cos_i, n0, n1, n2, w0, w1, w2, i0, i1, i2)
    wo_h = dot(w0, w1, w2, h0, h1, h2)
    wi_h = dot(i0, i1, i2, h0, h1, h2)
    if wo_h * cos_o <= 0.0 or wi_h * cos_i <= 0.0:
        return 0.0
    reflect = cos_o * cos_i > 0.0
    if reflect:
        jac = 1.0 / (4.0 * wi_h)
    else:
        den = wo_h + eta * wi_h
        jac = eta * eta * wi_h / (den * den)
    s = 1.0 if cos_o > 0.0 else -1.0
    p = visible_pdf(int(row[B_DIST]), row[B_ALPHA], s * cos_o, dot(n0, n1, n2, h0, h1, h2), s * wo_h)
    f = fresnel(wo_h, row[B_ETA])[0]
    return p * (f if reflect else 1.0 - f) * abs(jac)


# -- sampling ---------------------------------------------------------------------
@nb.njit(cache=True, error_model="numpy")
def sample_colour(kind, row, n0, n1, n2, w0, w1, w2, u1, u2, u3, radiance):
    """Sample wi as Mitsuba's `sample` does. Returns (ok, wi, weight rgb,
    eta_scale, delta): the path's throughput is multiplied by weight *
    eta_scale, where weight = f |cos_i| / pdf and eta_scale the 1/eta^2 of
    radiance leaving a rough dielectric by transmission (1 otherwise; kept
    apart so that Russian roulette can ignore it, as for GLASS)."""
    if kind == ROUGH_DIELECTRIC:
        return _sample_rough_dielectric(row, n0, n1, n2, w0, w1, w2, u1, u2, u3, radiance)
    cos_o = dot(n0, n1, n2, w0, w1, w2)
    if cos_o <= 0.0:
        return False, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0, False
    if kind == CONDUCTOR or kind == ROUGH_CONDUCTOR:
        return _sample_conductor(kind, row, n0, n1, n2, w0, w1, w2, cos_o, u2, u3)
    q = _plastic_probability(row, kind, cos_o)
    if kind == PLASTIC and u1 < q:
        k = fresnel(cos_o, row[B_ETA])[0] / q
        return (True, 2.0 * cos_o * n0 - w0, 2.0 * cos_o * n1 - w1, 2.0 * cos_o * n2 - w2,
                k * row[B_SPEC], k * row[B_SPEC + 1], k * row[B_SPEC + 2], 1.0, True)
    if u1 < q:
        m0, m1, m2 = sample_visible(int(row[B_DIST]), row[B_ALPHA], n0, n1, n2, w0, w1, w2, u2, u3)
        c = 2.0 * dot(w0, w1, w2, m0, m1, m2)
        i0, i1, i2 = c * m0 - w0, c * m1 - w1, c * m2 - w2
    else:
        x, y, z = cosine_hemisphere(u2, u3)
        i0, i1, i2 = to_world(x, y, z, n0, n1, n2)
    cos_i = dot(n0, n1, n2, i0, i1, i2)
    pdf = pdf_colour(kind, row, n0, n1, n2, w0, w1, w2, i0, i1, i2)
    if not (cos_i > 0.0 and pdf > 0.0):
        return False, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0, False
    f0, f1, f2 = eval_colour(kind, row, n0, n1, n2, w0, w1, w2, i0, i1, i2, radiance)
    k = cos_i / pdf
    return True, i0, i1, i2, f0 * k, f1 * k, f2 * k, 1.0, False


@nb.njit(cache=True, error_model="numpy")
def _sample_conductor(kind, row, n0, n1, n2, w0, w1, w2, cos_o, u2, u3):
    """A smooth conductor's mirror direction (weight F s, delta), or
    Mitsuba's roughconductor sample: a visible normal m, the reflection
    about it, weight F(wo.m) G1(wi, m) s."""
    if kind == CONDUCTOR:
        f0, f1, f2 = conductor_tint(row, cos_o)
        k = 2.0 * cos_o
        return True, k * n0 - w0, k * n1 - w1, k * n2 - w2, f0, f1, f2, 1.0, True
    dist, alpha = int(row[B_DIST]), row[B_ALPHA]
    m0, m1, m2 = sample_visible(dist, alpha, n0, n1, n2, w0, w1, w2, u2, u3)
    c = dot(w0, w1, w2, m0, m1, m2)
    i0, i1, i2 = 2.0 * c * m0 - w0, 2.0 * c * m1 - w1, 2.0 * c * m2 - w2
    cos_i = dot(n0, n1, n2, i0, i1, i2)
    g = smith_g1(dist, alpha, cos_i, dot(i0, i1, i2, m0, m1, m2)) if cos_i > 0.0 else 0.0
    if not g > 0.0:
        return False, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0, False
    f0, f1, f2 = conductor_tint(row, c)
    return True, i0, i1, i2, f0 * g, f1 * g, f2 * g, 1.0, False


@nb.njit(cache=True, error_model="numpy")
def _sample_rough_dielectric(row, n0, n1, n2, w0, w1, w2, u1, u2, u3, radiance):
    """Mitsuba's roughdielectric `sample` with visible normals: a microfacet
    m seen from wo, reflection with probability F(wo.m), else refraction;
    the weight is G1(wi, m) times the tint (and eta_ti^2 for radiance)."""
    cos_o = dot(n0, n1, n2, w0, w1, w2)
    if cos_o == 0.0:
        return False, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0, False
    s = 1.0 if cos_o > 0.0 else -1.0
    dist, alpha = int(row[B_DIST]), row[B_ALPHA]
    m0, m1, m2 = sample_visible(dist, alpha, n0, n1, n2, s * w0, s * w1, s * w2, u2, u3)
    wo_m = dot(w0, w1, w2, m0, m1, m2)
    f, cos_t, _eta_it, eta_ti = fresnel(wo_m, row[B_ETA])
    eta_scale = 1.0
    if u1 <= f:
        i0, i1, i2 = 2.0 * wo_m * m0 - w0, 2.0 * wo_m * m1 - w1, 2.0 * wo_m * m2 - w2
        tint = B_SPEC
    else:
        k = wo_m * eta_ti + cos_t
        i0, i1, i2 = m0 * k - w0 * eta_ti, m1 * k - w1 * eta_ti, m2 * k - w2 * eta_ti
        tint = B_REFL
        if radiance:
            eta_scale = eta_ti * eta_ti
    g = smith_g1(dist, alpha, dot(n0, n1, n2, i0, i1, i2), dot(i0, i1, i2, m0, m1, m2))
    if not g > 0.0:
        return False, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0, False
    return (True, i0, i1, i2, g * row[tint], g * row[tint + 1], g * row[tint + 2], eta_scale, False)


# -- what a hit point sees ------------------------------------------------------------
@nb.njit(cache=True, error_model="numpy")
def hit_point_eval(kind, row, n0, n1, n2, w0, w1, w2, i0, i1, i2):
    """f (rgb, radiance transport) of a hit point of this kind, for the
    gather and direct light: the BSDF, except that a smooth plastic's hit
    point stands for its base alone, chosen with probability 1 - q(wo)
    (see the module notes), hence f_base / (1 - q)."""
    f0, f1, f2 = eval_colour(kind, row, n0, n1, n2, w0, w1, w2, i0, i1, i2, True)
    if kind == PLASTIC:
        q = _plastic_probability(row, kind, dot(n0, n1, n2, w0, w1, w2))
        k = 1.0 / (1.0 - q) if q < 1.0 else 0.0
        return f0 * k, f1 * k, f2 * k
    return f0, f1, f2


# -- decisions an eye path makes at a surface -----------------------------------------
_SALT = np.uint64(0xD1B54A32D192ED03)


@nb.njit(cache=True, error_model="numpy")
def side_float(state, salt):
    """A uniform number from the path's state that `next_float` never
    yields: an eye path that stores a hit point hands its state on to the
    hit point's direct-light sample, so a choice made here (a mask, a
    plastic's lobe) must not reuse the numbers that sample will draw."""
    z = mix64(np.uint64(state) ^ (_SALT * np.uint64(salt + 1)))
    return np.float32(z >> np.uint64(40)) * np.float32(1.0 / (1 << 24))


@nb.njit(cache=True, error_model="numpy")
def hit_point_sample(kind, row, n0, n1, n2, w0, w1, w2, u1, u2, u3):
    """A direction from the hit point's BSDF (`hit_point_eval`) for direct
    light: a smooth plastic's base by its cosine, else `sample_colour`.
    Returns (ok, wi, weight rgb)."""
    if kind == PLASTIC:
        x, y, z = cosine_hemisphere(u2, u3)
        i0, i1, i2 = to_world(x, y, z, n0, n1, n2)
        return True, i0, i1, i2, 1.0, 1.0, 1.0
    ok, i0, i1, i2, t0, t1, t2, eta_scale, _delta = sample_colour(kind, row, n0, n1, n2, w0, w1, w2,
                                                                  u1, u2, u3, True)
    return ok, i0, i1, i2, t0 * eta_scale, t1 * eta_scale, t2 * eta_scale


@nb.njit(cache=True, error_model="numpy")
def hit_point_pdf(kind, row, n0, n1, n2, w0, w1, w2, i0, i1, i2):
    """Density of `hit_point_sample`."""
    if kind == PLASTIC:
        return max(0.0, dot(n0, n1, n2, i0, i1, i2)) * INV_PI
    return pdf_colour(kind, row, n0, n1, n2, w0, w1, w2, i0, i1, i2)


def gather_tint(materials) -> np.ndarray:
    """(m, 3) float64: what a gather multiplies a hit point's sum of
    f * flux by at the end: the reflectance of the older kinds (their f is
    a scalar times it), 1 for the coloured ones (their f is already RGB)."""
    tint = np.array(materials.reflectance, np.float64)
    tint[(materials.kind >= ROUGH_DIELECTRIC) & (materials.kind <= ROUGH_CONDUCTOR)] = 1.0
    return tint


@nb.njit(inline="always", cache=True, error_model="numpy")
def gather_f(kind, alpha, bsdf, mat, n0, n1, n2, w0, w1, w2, i0, i1, i2):
    """What a gather weighs a photon from wi by at a hit point of material
    mat (rgb): the older kinds' scalar f (their reflectance multiplies the
    sum at the end, `gather_tint`), the coloured kinds' `hit_point_eval`.
    Inlined into the gathers' loops, so no call takes an array per photon."""
    if kind == DIFFUSE:     # the common case
        return INV_PI, INV_PI, INV_PI
    if is_coloured(kind):
        return hit_point_eval(kind, bsdf[mat], n0, n1, n2, w0, w1, w2, i0, i1, i2)
    f = eval_bsdf(kind, alpha, n0, n1, n2, w0, w1, w2, i0, i1, i2)
    return f, f, f


# -- masks and blends: what scatters at a hit ------------------------------------------
# Nesting deeper than this (a mask of a blend of blends ...) is refused by the reader.
MAX_NESTING = 4


@nb.njit(cache=True, error_model="numpy")
def scalar_at(row, col, tex_col, uvs, tris, tinfo, tuv, texels, tri, u, v):
    """A [0, 1] parameter of the row: the constant, or the texture's
    luminance at the hit clipped to [0, 1] (Mitsuba's eval_1 of an RGB
    texture; a grey one gives its value)."""
    t = int(row[tex_col])
    if t < 0:
        return row[col]
    c0, c1, c2 = texel_at(uvs, tris, tinfo, tuv, texels, t, tri, u, v)
    return min(1.0, max(0.0, 0.212671 * c0 + 0.715160 * c1 + 0.072169 * c2))


@nb.njit(cache=True, error_model="numpy")
def _draw(state, eye, salt):
    """(state, u): an eye path's choice from its side stream (`side_float`,
    state unchanged), a photon's from its stream."""
    if eye:
        return state, side_float(state, salt)
    return next_float(state)


@nb.njit(cache=True, error_model="numpy")
def resolve_surface(bsdf, m, state, eye, uvs, tris, tinfo, tuv, texels, tri, u, v):
    """What a ray meets at a hit on material m, for materials whose row has
    CHOICE set: (state, the material that scatters, whether the ray passes
    straight through). A mask is there with probability opacity (Mitsuba's
    mask.cpp samples its null lobe with 1 - opacity, weight 1); a blend
    hands the interaction to its second material with probability weight
    (blendbsdf.cpp samples its lobes so, weight 1). Both are read at the
    hit's UV when textured, so eye rays and photons see the same surface.
    Not inlined: it is rare, and it takes the texture arrays."""
    for level in range(MAX_NESTING):
        row = bsdf[m]
        if row[B_OPACITY] < 1.0:
            a = scalar_at(row, B_OPACITY, B_OPACITY_TEX, uvs, tris, tinfo, tuv, texels, tri, u, v)
            # salt 0: the first mask's choice as before blends existed; 1 is plastic's.
            state, x = _draw(state, eye, 0 if level == 0 else 2 + 2 * level)
            if x >= a:
                return state, m, True
        if row[B_BLEND_B] < 0.0:
            return state, m, False
        w = scalar_at(row, B_BLEND_W, B_BLEND_TEX, uvs, tris, tinfo, tuv, texels, tri, u, v)
        state, x = _draw(state, eye, 3 + 2 * level)
        m = int(row[B_BLEND_B]) if x < w else int(row[B_BLEND_A])
    return state, m, False
