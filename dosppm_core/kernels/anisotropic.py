"""Mitsuba 3's rough conductor with anisotropic or textured roughness
(src/bsdfs/roughconductor.cpp with alpha_u != alpha_v, or alpha_u and
alpha_v read from textures at the hit), in the local frame (s, t, n) of
the surface: alpha_u along s, alpha_v along t.

The frame is Mitsuba's shading frame: s = dp/du made orthogonal to the
normal n, t = n x s (mesh.cpp's dp/du, `shading.tangents`); under a
normal map n is the perturbed normal and s dp/du made orthogonal to it,
as normalmap.cpp builds its frame. An isotropic rough conductor never
comes here (`is_anisotropic` false: `materials` evaluates it about any
frame, as before), so isotropic scenes compute exactly what they did.

Vectors in and out of the `*_local` functions are local: (x, y, z) =
(v.s, v.t, v.n), with wo the direction back along the arriving ray and
wi the scattered one, as in `bsdf.py`.
"""
import math

import numba as nb
import numpy as np

from dosppm_core.kernels.materials import (
    B_ALPHA,
    B_ALPHA_TEX_U,
    B_ALPHA_TEX_V,
    B_ALPHA_V,
    B_ANISO,
    B_DIST,
    conductor_tint,
    gather_f,
    hit_point_eval,
    hit_point_pdf,
    hit_point_sample,
    scalar_at,
)
from dosppm_core.kernels.microfacet import distribution_d_aniso, sample_visible_aniso, smith_g1_aniso
from dosppm_core.kernels.shading import tangents
from dosppm_core.kernels.texture import LUMINANCE
from dosppm_core.scene.model import ROUGH_CONDUCTOR
from dosppm_core.scene.textures import CHECKERBOARD, INFO_KIND, INFO_OFFSET

_NONE = (False, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0)


@nb.njit(inline="always", cache=True, error_model="numpy")
def is_anisotropic(bsdf, m):
    """Whether material m needs a tangent frame (and maybe its textures)."""
    return bsdf[m, B_ANISO] > 0.0


@nb.njit(cache=True, error_model="numpy")
def frame(du0, du1, du2, n0, n1, n2):
    """(s, t) of the frame about unit n whose s is dp/du made orthogonal
    to n (Mitsuba's sh_frame.s); any tangent when dp/du is parallel to n."""
    k = n0 * du0 + n1 * du1 + n2 * du2
    s0, s1, s2 = du0 - k * n0, du1 - k * n1, du2 - k * n2
    sl = math.sqrt(s0 * s0 + s1 * s1 + s2 * s2)
    if not sl > 0.0:
        s0, s1, s2 = (1.0, 0.0, 0.0) if abs(n0) < 0.9 else (0.0, 1.0, 0.0)
        k = n0 * s0 + n1 * s1 + n2 * s2
        s0, s1, s2 = s0 - k * n0, s1 - k * n1, s2 - k * n2
        sl = math.sqrt(s0 * s0 + s1 * s1 + s2 * s2)
    s0, s1, s2 = s0 / sl, s1 / sl, s2 / sl
    return (s0, s1, s2), (n1 * s2 - n2 * s1, n2 * s0 - n0 * s2, n0 * s1 - n1 * s0)


@nb.njit(cache=True, error_model="numpy")
def _eval_1(row, col, tex_col, uvs, tris, tinfo, tuv, texels, tri, u, v):
    """Mitsuba's eval_1 of the parameter: `materials.scalar_at`, except
    that a checkerboard gives the other colour. Mitsuba 3's checkerboard
    eval_1 (what roughconductor reads its alphas with) returns color1
    where its eval returns color0 and vice versa (3.9.1, checked in
    tests/test_anisotropic.py), and its reference images show it."""
    value = scalar_at(row, col, tex_col, uvs, tris, tinfo, tuv, texels, tri, u, v)
    t = int(row[tex_col])
    if t < 0 or tinfo[t, INFO_KIND] != CHECKERBOARD:
        return value
    off = tinfo[t, INFO_OFFSET]
    c0 = LUMINANCE[0] * texels[off, 0] + LUMINANCE[1] * texels[off, 1] + LUMINANCE[2] * texels[off, 2]
    c1 = LUMINANCE[0] * texels[off + 1, 0] + LUMINANCE[1] * texels[off + 1, 1] + LUMINANCE[2] * texels[off + 1, 2]
    c0, c1 = min(1.0, max(0.0, c0)), min(1.0, max(0.0, c1))
    return c1 if value == c0 else c0


@nb.njit(cache=True, error_model="numpy")
def alphas(row, uvs, tris, tinfo, tuv, texels, tri, u, v):
    """(alpha_u, alpha_v) of the material at the hit: its constants, or
    its textures' values there (Mitsuba's eval_1), at least 1e-4."""
    au = _eval_1(row, B_ALPHA, B_ALPHA_TEX_U, uvs, tris, tinfo, tuv, texels, tri, u, v)
    av = _eval_1(row, B_ALPHA_V, B_ALPHA_TEX_V, uvs, tris, tinfo, tuv, texels, tri, u, v)
    return max(au, 1e-4), max(av, 1e-4)


@nb.njit(cache=True, error_model="numpy")
def _half(ox, oy, oz, ix, iy, iz):
    hx, hy, hz = ox + ix, oy + iy, oz + iz
    hl = math.sqrt(hx * hx + hy * hy + hz * hz)
    return hx / hl, hy / hl, hz / hl


@nb.njit(cache=True, error_model="numpy")
def eval_local(row, au, av, ox, oy, oz, ix, iy, iz):
    """f (rgb, without the cosine): F(wo.h) D(h) G1(wo) G1(wi) / (4 cos_o cos_i)."""
    if oz <= 0.0 or iz <= 0.0:
        return 0.0, 0.0, 0.0
    dist = int(row[B_DIST])
    hx, hy, hz = _half(ox, oy, oz, ix, iy, iz)
    wo_h = ox * hx + oy * hy + oz * hz
    g = smith_g1_aniso(dist, au, av, ox, oy, oz, wo_h) * \
        smith_g1_aniso(dist, au, av, ix, iy, iz, ix * hx + iy * hy + iz * hz)
    k = distribution_d_aniso(dist, au, av, hx, hy, hz) * g / (4.0 * oz * iz)
    f0, f1, f2 = conductor_tint(row, wo_h)
    return f0 * k, f1 * k, f2 * k


@nb.njit(cache=True, error_model="numpy")
def pdf_local(row, au, av, ox, oy, oz, ix, iy, iz):
    """Density of `sample_local`: D(h) G1(wo, h) / (4 cos_o) (visible normals)."""
    if oz <= 0.0 or iz <= 0.0:
        return 0.0
    dist = int(row[B_DIST])
    hx, hy, hz = _half(ox, oy, oz, ix, iy, iz)
    wo_h = ox * hx + oy * hy + oz * hz
    if wo_h <= 0.0:
        return 0.0
    return distribution_d_aniso(dist, au, av, hx, hy, hz) * \
        smith_g1_aniso(dist, au, av, ox, oy, oz, wo_h) / (4.0 * oz)


@nb.njit(cache=True, error_model="numpy")
def sample_local(row, au, av, ox, oy, oz, u2, u3):
    """Mitsuba's sample: a visible normal m, wi the reflection of wo about
    it, weight F(wo.m) G1(wi, m). Returns (ok, wi, weight rgb)."""
    if oz <= 0.0:
        return _NONE
    dist = int(row[B_DIST])
    mx, my, mz = sample_visible_aniso(dist, au, av, ox, oy, oz, u2, u3)
    c = ox * mx + oy * my + oz * mz
    ix, iy, iz = 2.0 * c * mx - ox, 2.0 * c * my - oy, 2.0 * c * mz - oz
    g = smith_g1_aniso(dist, au, av, ix, iy, iz, ix * mx + iy * my + iz * mz) if iz > 0.0 else 0.0
    if not g > 0.0:
        return _NONE
    f0, f1, f2 = conductor_tint(row, c)
    return True, ix, iy, iz, f0 * g, f1 * g, f2 * g


# -- world space: a frame (s, t, n) as three 3-tuples ---------------------------------
@nb.njit(cache=True, error_model="numpy")
def to_local(s, t, n, w0, w1, w2):
    return (s[0] * w0 + s[1] * w1 + s[2] * w2, t[0] * w0 + t[1] * w1 + t[2] * w2,
            n[0] * w0 + n[1] * w1 + n[2] * w2)


@nb.njit(cache=True, error_model="numpy")
def eval_world(row, au, av, s, t, n, w0, w1, w2, i0, i1, i2):
    ox, oy, oz = to_local(s, t, n, w0, w1, w2)
    ix, iy, iz = to_local(s, t, n, i0, i1, i2)
    return eval_local(row, au, av, ox, oy, oz, ix, iy, iz)


@nb.njit(cache=True, error_model="numpy")
def pdf_world(row, au, av, s, t, n, w0, w1, w2, i0, i1, i2):
    ox, oy, oz = to_local(s, t, n, w0, w1, w2)
    ix, iy, iz = to_local(s, t, n, i0, i1, i2)
    return pdf_local(row, au, av, ox, oy, oz, ix, iy, iz)


@nb.njit(cache=True, error_model="numpy")
def sample_world(row, au, av, s, t, n, w0, w1, w2, u2, u3):
    """`sample_local` in world space: (ok, wi, weight rgb)."""
    ox, oy, oz = to_local(s, t, n, w0, w1, w2)
    ok, ix, iy, iz, f0, f1, f2 = sample_local(row, au, av, ox, oy, oz, u2, u3)
    return (ok, ix * s[0] + iy * t[0] + iz * n[0], ix * s[1] + iy * t[1] + iz * n[1],
            ix * s[2] + iy * t[2] + iz * n[2], f0, f1, f2)


# -- at a surface point ---------------------------------------------------------------
@nb.njit(cache=True, error_model="numpy")
def surface_lobe(surf, m, tri, u, v, n0, n1, n2):
    """(s, t, alpha_u, alpha_v) of material m at barycentrics (u, v) of
    triangle tri, whose (shading) normal n faces the arriving ray."""
    du, _dv = tangents(surf.vertices, surf.triangles, surf.uvs, tri, n0, n1, n2)
    s, t = frame(du[0], du[1], du[2], n0, n1, n2)
    au, av = alphas(surf.bsdf[m], surf.uvs, surf.triangles, surf.tex_info, surf.tex_uv, surf.texels,
                    tri, np.float64(u), np.float64(v))
    return s, t, au, av


@nb.njit(cache=True, error_model="numpy")
def scatter(surf, m, tri, u, v, n0, n1, n2, w0, w1, w2, u2, u3):
    """A photon's bounce off an anisotropic conductor (n: its shading
    normal, turned to face w as `paths.sample_scatter` does for a
    two-sided one): (ok, direction, throughput rgb)."""
    if n0 * w0 + n1 * w1 + n2 * w2 < 0.0:
        n0, n1, n2 = -n0, -n1, -n2
    s, t, au, av = surface_lobe(surf, m, tri, u, v, n0, n1, n2)
    return sample_world(surf.bsdf[m], au, av, s, t, (n0, n1, n2), w0, w1, w2, u2, u3)


@nb.njit(cache=True, parallel=True, error_model="numpy")
def hit_point_frames(surf, prim, material, u, v, normal):
    """float64 (n, 5) per hit point: s (3), alpha_u, alpha_v where its
    material (`material`: what a mask or blend chose) is anisotropic, about
    its stored normal (facing the eye, perturbed by a normal map); zeros
    elsewhere. What `direct` needs besides the hit point (t = n x s).
    The `hp_*` below are not inlined: inlined into the parallel direct
    kernel, numba's parfor array analysis failed on them ("Dimension
    mismatch"), and they cost a call only at coloured hit points."""
    n = prim.shape[0]
    out = np.zeros((n, 5))
    for i in nb.prange(n):
        m = material[i]
        if not is_anisotropic(surf.bsdf, m):
            continue
        s, _t, au, av = surface_lobe(surf, m, prim[i], u[i], v[i], np.float64(normal[i, 0]),
                                     np.float64(normal[i, 1]), np.float64(normal[i, 2]))
        out[i, 0], out[i, 1], out[i, 2], out[i, 3], out[i, 4] = s[0], s[1], s[2], au, av
    return out


@nb.njit(cache=True, error_model="numpy")
def _hit_frame(frames, i, n0, n1, n2):
    s = (frames[i, 0], frames[i, 1], frames[i, 2])
    return s, (n1 * s[2] - n2 * s[1], n2 * s[0] - n0 * s[2], n0 * s[1] - n1 * s[0]), frames[i, 3], frames[i, 4]


@nb.njit(cache=True, error_model="numpy")
def hp_eval(kind, row, frames, i, n0, n1, n2, w0, w1, w2, i0, i1, i2):
    """`materials.hit_point_eval`, in hit point i's frame when anisotropic."""
    if row[B_ANISO] > 0.0:
        s, t, au, av = _hit_frame(frames, i, n0, n1, n2)
        return eval_world(row, au, av, s, t, (n0, n1, n2), w0, w1, w2, i0, i1, i2)
    return hit_point_eval(kind, row, n0, n1, n2, w0, w1, w2, i0, i1, i2)


@nb.njit(cache=True, error_model="numpy")
def hp_pdf(kind, row, frames, i, n0, n1, n2, w0, w1, w2, i0, i1, i2):
    """`materials.hit_point_pdf`, likewise."""
    if row[B_ANISO] > 0.0:
        s, t, au, av = _hit_frame(frames, i, n0, n1, n2)
        return pdf_world(row, au, av, s, t, (n0, n1, n2), w0, w1, w2, i0, i1, i2)
    return hit_point_pdf(kind, row, n0, n1, n2, w0, w1, w2, i0, i1, i2)


@nb.njit(cache=True, error_model="numpy")
def hp_sample(kind, row, frames, i, n0, n1, n2, w0, w1, w2, u1, u2, u3):
    """`materials.hit_point_sample`, likewise."""
    if row[B_ANISO] > 0.0:
        s, t, au, av = _hit_frame(frames, i, n0, n1, n2)
        return sample_world(row, au, av, s, t, (n0, n1, n2), w0, w1, w2, u2, u3)
    return hit_point_sample(kind, row, n0, n1, n2, w0, w1, w2, u1, u2, u3)


# -- the gather -------------------------------------------------------------------------
@nb.njit(cache=True, error_model="numpy")
def framed_f(row, s0, s1, s2, au, av, n0, n1, n2, w0, w1, w2, i0, i1, i2):
    """f (rgb) of an anisotropic hit point whose frame (`hit_point_frames`)
    is s, alpha_u, alpha_v, about its normal n: what direct light weighs
    the same hit point by (`hp_eval`). Called only at such hit points, so
    the gathers' common path takes no call with an array."""
    t = (n1 * s2 - n2 * s1, n2 * s0 - n0 * s2, n0 * s1 - n1 * s0)
    return eval_world(row, au, av, (s0, s1, s2), t, (n0, n1, n2), w0, w1, w2, i0, i1, i2)


@nb.njit(inline="always", cache=True, error_model="numpy")
def has_frame(kind, bsdf, mat, frames, h):
    """Whether hit point h (material mat of `kind`) is gathered in its frame
    `frames[h]`: its material is anisotropic or has textured roughness.
    `frames` is `HitPoints.frame`, or None in a scene without one: numba
    then compiles the gathers without the framed branch (as `extras`
    prunes the bounces)."""
    if frames is None:
        return False
    return kind == ROUGH_CONDUCTOR and h < frames.shape[0] and bsdf[mat, B_ANISO] > 0.0


@nb.njit(inline="always", cache=True, error_model="numpy")
def gather_f_framed(framed, kind, alpha, bsdf, mat, frames, h, n0, n1, n2, w0, w1, w2, i0, i1, i2):
    """`materials.gather_f` of hit point h, in its frame where `framed`
    (`has_frame`, which a caller may ask once per hit point). The test of
    None repeats has_frame's on purpose: numba prunes a branch only on a
    test of an argument itself, and without it would type frames[h, 0] on
    None."""
    if frames is not None and framed:
        return framed_f(bsdf[mat], np.float64(frames[h, 0]), np.float64(frames[h, 1]),
                        np.float64(frames[h, 2]), np.float64(frames[h, 3]), np.float64(frames[h, 4]),
                        n0, n1, n2, w0, w1, w2, i0, i1, i2)
    return gather_f(kind, alpha, bsdf, mat, n0, n1, n2, w0, w1, w2, i0, i1, i2)


def frames_of(hp) -> np.ndarray | None:
    """The gathers' `frames` argument for hit points `hp`: float32 (n, 5),
    or None (the gathers compiled without frames)."""
    return None if hp.frame is None else np.ascontiguousarray(hp.frame, np.float32)
