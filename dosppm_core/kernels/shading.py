"""Normal and bump maps: the shading normal of Mitsuba 3's `normalmap`
and `bumpmap` wrappers (src/bsdfs/normalmap.cpp, bumpmap.cpp, v3.9), and
how photons and eye paths use it.

The unperturbed frame is the triangle's: n its unit CCW normal (Mitsuba's
sh_frame.n on a flat mesh; on a smooth one Mitsuba would start from the
interpolated vertex normal, `kernels.smooth`, which a mapped material
ignores here), s the tangent dp/du made orthogonal to n,
t = n x s. dp/du and dp/dv come from the triangle's positions and UVs as
Mitsuba's mesh computes them (p1 - p0 and p2 - p0 without UVs, an
arbitrary basis where the UVs are degenerate). Then

* normalmap: the local normal 2 c - 1 of the texel c (read raw);
* bumpmap: dp/du + n g_u and dp/dv + n g_v, g the height texture's UV
  gradient times `scale`; their cross product, turned to n's side, in the
  local frame;
* flip_invalid_normals: a local normal (x, y, z) that the eye direction sees
  from behind becomes (-x, -y, z);
* use_shadowing_function: the nested BSDF's value is multiplied by
  Estevez et al.'s G(wi) = 2 / (1 + sqrt(1 + a2 tan^2 wi)), with
  a2 = min(tan^2(perturbed normal) / 8, 1), wi the light-side direction;
  and light is counted only where wi lies on the same side of n and of the
  perturbed normal.

A back-side hit of a two-sided material mirrors all this through the
tangent plane, as Mitsuba's `twosided` does around the wrapper.

Where it is used (only in scenes with such a material; every other scene
runs none of this): an eye path's hit point stores the perturbed normal
in place of its geometric one (`perturb_hit_points`, after the bounce),
and its direct-light rays are multiplied by G and the side test
(`terminator_factor`); the gather evaluates the nested BSDF with the
stored normal. Photons read the same normal at their hits (without the
flip, which depends on an eye direction they do not have) and carry
Veach's adjoint of the shading-normal BSDF (Veach 1997, 5.3): a photon
arriving from wi and leaving to wo is weighted by
f |wi.ns| G(wi) |wo.ng| / (|wi.ng| p(wo)) instead of f |wo.ns| / p(wo),
and a deposit's flux by G(wi) |wi.ns| / |wi.ng|, the radiance it stands
for being measured through the geometric surface.

Where this differs from Mitsuba's path tracer (measured: both Mitsuba
test scenes pass its own scorer, and light off a mapped floor agrees
within 4%, `tests/test_normal_maps.py`):
* the unperturbed normal is the face's, not the vertex normals'
  interpolation, even on a smooth mesh;
* a photon samples its next direction around the unflipped normal, so
  it never leaves into directions where Mitsuba's frame would flip
  (grazing ones below the perturbed horizon): a little indirect light is
  missing there;
* a gathered photon carries the factor of the shading normal at its own
  point, not at the hit point's (the same surface within the radius, so
  exact as the radius shrinks), and the unflipped one.
"""
import math

import numba as nb
import numpy as np

from dosppm_core.kernels.bsdf import basis
from dosppm_core.kernels.materials import B_BUMP_MAP, B_BUMP_SCALE, B_NORMAL_MAP, B_SHADING_FLAGS
from dosppm_core.kernels.texture import height_gradient, hit_uv, texel

FLIP_INVALID, SHADOWING = 1, 2      # bits of `Material.shading_flags`


@nb.njit(inline="always", cache=True, error_model="numpy")
def is_mapped(bsdf, m):
    """Whether material m has a normal or a bump map."""
    return bsdf[m, B_NORMAL_MAP] >= 0.0 or bsdf[m, B_BUMP_MAP] >= 0.0


@nb.njit(cache=True, error_model="numpy")
def tangents(verts, tris, uvs, tri, n0, n1, n2):
    """Mitsuba's (dp/du, dp/dv) of triangle tri (unit normal n)."""
    t0, t1, t2 = tris[tri, 0], tris[tri, 1], tris[tri, 2]
    a0 = np.float64(verts[t1, 0]) - verts[t0, 0]
    a1 = np.float64(verts[t1, 1]) - verts[t0, 1]
    a2 = np.float64(verts[t1, 2]) - verts[t0, 2]
    b0 = np.float64(verts[t2, 0]) - verts[t0, 0]
    b1 = np.float64(verts[t2, 1]) - verts[t0, 1]
    b2 = np.float64(verts[t2, 2]) - verts[t0, 2]
    if uvs.shape[0] == 0:
        return (a0, a1, a2), (b0, b1, b2)
    du0, dv0 = np.float64(uvs[t1, 0]) - uvs[t0, 0], np.float64(uvs[t1, 1]) - uvs[t0, 1]
    du1, dv1 = np.float64(uvs[t2, 0]) - uvs[t0, 0], np.float64(uvs[t2, 1]) - uvs[t0, 1]
    det = du0 * dv1 - dv0 * du1
    if det == 0.0:
        return basis(n0, n1, n2)
    k = 1.0 / det
    return (((dv1 * a0 - dv0 * b0) * k, (dv1 * a1 - dv0 * b1) * k, (dv1 * a2 - dv0 * b2) * k),
            ((du0 * b0 - du1 * a0) * k, (du0 * b1 - du1 * a1) * k, (du0 * b2 - du1 * a2) * k))


@nb.njit(cache=True, error_model="numpy")
def _normalise(x, y, z):
    k = 1.0 / math.sqrt(x * x + y * y + z * z)
    return x * k, y * k, z * k


@nb.njit(cache=True, error_model="numpy")
def _local_normal(bsdf, m, du, dv, n, tex, tri, u, v):
    """The perturbed normal in the frame (s, t, n) of dp/du: a normal map's
    2 c - 1, or the bump map's normal; also returns s and t."""
    uvs, tris, tinfo, tuv, texels = tex
    n0, n1, n2 = n
    k = n0 * du[0] + n1 * du[1] + n2 * du[2]
    s0, s1, s2 = _normalise(du[0] - k * n0, du[1] - k * n1, du[2] - k * n2)
    t0, t1, t2 = n1 * s2 - n2 * s1, n2 * s0 - n0 * s2, n0 * s1 - n1 * s0
    su, sv = hit_uv(uvs, tris, tri, u, v) if uvs.shape[0] else (u, v)   # no UVs: Mitsuba's (b1, b2)
    nmap = int(bsdf[m, B_NORMAL_MAP])
    if nmap >= 0:
        c0, c1, c2 = texel(tinfo, tuv, texels, nmap, su, sv)
        return 2.0 * c0 - 1.0, 2.0 * c1 - 1.0, 2.0 * c2 - 1.0, (s0, s1, s2), (t0, t1, t2)
    gu, gv = height_gradient(tinfo, tuv, texels, int(bsdf[m, B_BUMP_MAP]), su, sv)
    scale = bsdf[m, B_BUMP_SCALE]
    ku = scale * gu - (n0 * du[0] + n1 * du[1] + n2 * du[2])
    kv = scale * gv - (n0 * dv[0] + n1 * dv[1] + n2 * dv[2])
    p0, p1, p2 = du[0] + ku * n0, du[1] + ku * n1, du[2] + ku * n2
    q0, q1, q2 = dv[0] + kv * n0, dv[1] + kv * n1, dv[2] + kv * n2
    b0, b1, b2 = _normalise(p1 * q2 - p2 * q1, p2 * q0 - p0 * q2, p0 * q1 - p1 * q0)
    if b0 * n0 + b1 * n1 + b2 * n2 < 0.0:
        b0, b1, b2 = -b0, -b1, -b2
    return (b0 * s0 + b1 * s1 + b2 * s2, b0 * t0 + b1 * t1 + b2 * t2, b0 * n0 + b1 * n1 + b2 * n2,
            (s0, s1, s2), (t0, t1, t2))


@nb.njit(cache=True, error_model="numpy")
def shading_normal(bsdf, m, verts, tex, tri, u, v, n0, n1, n2, front, w0, w1, w2, flip):
    """(perturbed unit normal on the side the hit faces, a2 of the
    shadowing function) of material m at barycentrics (u, v) of triangle
    tri (unit CCW normal n). `w` is the eye-side direction, which decides
    flip_invalid_normals when `flip` (eye paths) is true. `tex` is
    (uvs, triangles, tex_info, tex_uv, texels)."""
    du, dv = tangents(verts, tex[1], tex[0], tri, n0, n1, n2)
    x, y, z, s, t = _local_normal(bsdf, m, du, dv, (n0, n1, n2), tex, tri, np.float64(u), np.float64(v))
    f0, f1, f2 = (n0, n1, n2) if front else (-n0, -n1, -n2)     # twosided: the mirror image
    flags = int(bsdf[m, B_SHADING_FLAGS])
    if flip and flags & FLIP_INVALID:
        wz = w0 * f0 + w1 * f1 + w2 * f2
        if wz * ((w0 * s[0] + w1 * s[1] + w2 * s[2]) * x + (w0 * t[0] + w1 * t[1] + w2 * t[2]) * y
                 + wz * z) <= 0.0:
            x, y = -x, -y
    x, y, z = _normalise(x, y, z)
    a2 = 0.0
    if flags & SHADOWING:
        a2 = min(0.125 * max(0.0, 1.0 - z * z) / (z * z), 1.0)
    return (x * s[0] + y * t[0] + z * f0, x * s[1] + y * t[1] + z * f1,
            x * s[2] + y * t[2] + z * f2, a2)


@nb.njit(inline="always", cache=True, error_model="numpy")
def terminator(a2, cos_g):
    """Estevez et al.'s shadowing G of a light-side direction at cosine
    cos_g to the unperturbed normal; 1 when a2 = 0 (no shadowing)."""
    if a2 == 0.0:
        return 1.0
    c2 = cos_g * cos_g
    if not c2 > 0.0:
        return 0.0
    return 2.0 / (1.0 + math.sqrt(1.0 + a2 * max(0.0, 1.0 - c2) / c2))


@nb.njit(cache=True, error_model="numpy")
def photon_factor(a2, s0, s1, s2, g0, g1, g2, w0, w1, w2):
    """G(wi) |wi.ns| / |wi.ng| of a photon from wi at a hit of shading
    normal ns and facing geometric normal ng: what its deposit's flux and
    (times |wo.ng| / |wo.ns|) its scattered flux are multiplied by; zero
    unless wi lies above both."""
    cg = w0 * g0 + w1 * g1 + w2 * g2
    cs = w0 * s0 + w1 * s1 + w2 * s2
    if not (cg > 0.0 and cs > 0.0):
        return 0.0
    return terminator(a2, cg) * cs / cg


@nb.njit(cache=True, error_model="numpy")
def photon_shading(bsdf, m, verts, tex, tri, u, v, n0, n1, n2, front, w0, w1, w2):
    """(perturbed normal ns, `photon_factor`) at a photon's hit from w on
    material m (triangle normal n; `tex` as for `shading_normal`)."""
    s0, s1, s2, a2 = shading_normal(bsdf, m, verts, tex, tri, u, v, n0, n1, n2, front, w0, w1, w2, False)
    g = 1.0 if front else -1.0
    return s0, s1, s2, photon_factor(a2, s0, s1, s2, g * n0, g * n1, g * n2, w0, w1, w2)


@nb.njit(cache=True, parallel=True, error_model="numpy")
def perturb_hit_points(surf, prim, material, u, v, normal, outgoing):
    """Hit points' normals (float32 (n, 3), facing their outgoing
    direction, changed in place) replaced by their materials' (`material`:
    what a mask or blend chose there) perturbed
    normals. Returns (geometric normals before the change, a2 of each:
    -1 where the material has no map)."""
    n = prim.shape[0]
    geometric = normal.copy()
    a2 = np.full(n, -1.0)
    tex = (surf.uvs, surf.triangles, surf.tex_info, surf.tex_uv, surf.texels)
    for i in nb.prange(n):
        m = material[i]
        if not is_mapped(surf.bsdf, m):
            continue
        g0, g1, g2 = _ccw_normal(surf.vertices, surf.triangles, prim[i])
        front = g0 * normal[i, 0] + g1 * normal[i, 1] + g2 * normal[i, 2] > 0.0
        s0, s1, s2, a2[i] = shading_normal(surf.bsdf, m, surf.vertices, tex, prim[i], u[i], v[i],
                                           g0, g1, g2, front, outgoing[i, 0], outgoing[i, 1],
                                           outgoing[i, 2], True)
        normal[i, 0], normal[i, 1], normal[i, 2] = s0, s1, s2
    return geometric, a2


@nb.njit(cache=True, error_model="numpy")
def _ccw_normal(verts, tris, tri):
    t0, t1, t2 = tris[tri, 0], tris[tri, 1], tris[tri, 2]
    a0, a1, a2 = (np.float64(verts[t1, 0]) - verts[t0, 0], np.float64(verts[t1, 1]) - verts[t0, 1],
                  np.float64(verts[t1, 2]) - verts[t0, 2])
    b0, b1, b2 = (np.float64(verts[t2, 0]) - verts[t0, 0], np.float64(verts[t2, 1]) - verts[t0, 1],
                  np.float64(verts[t2, 2]) - verts[t0, 2])
    return _normalise(a1 * b2 - a2 * b1, a2 * b0 - a0 * b2, a0 * b1 - a1 * b0)


def terminator_factor(direction, geometric, a2) -> np.ndarray:
    """Per direct-light ray: 1 for a hit point without a map (a2 < 0),
    else G(wi) where wi lies above the geometric normal and 0 below it (the
    nested BSDF, evaluated with the perturbed normal, requires wi above
    that one already)."""
    c = np.einsum("ij,ij->i", direction.astype(np.float64), geometric.astype(np.float64))
    out = np.ones(len(c))
    mapped = a2 >= 0
    out[mapped & ~(c > 0)] = 0.0
    shadowed = np.flatnonzero(mapped & (c > 0) & (a2 > 0))
    c2 = c[shadowed] ** 2
    out[shadowed] = 2.0 / (1.0 + np.sqrt(1.0 + a2[shadowed] * np.maximum(0.0, 1.0 - c2) / c2))
    return out
