"""Texture lookups at a hit: the reflectance a textured material has there.

A hit on triangle `tri` at barycentrics (u, v) has the texture coordinate
interpolated from its vertices' UVs; `texel` evaluates texture t there as
Mitsuba 3's bitmap and checkerboard do (`scene.textures`). Photon bounces,
eye bounces and hit points all go through `texel_at`'s lookup, so photons
and eye rays read the same texel.

Where the texel goes: an eye path's hit point keeps it folded into its
weight (`fold_texels`), and a textured material's `reflectance` row is
(1, 1, 1). The gather and next-event estimation multiply weight by
reflectance, so they read the texel with no change, the hit-point record
and the wire keep their format, and an untextured scene runs no extra
code at its hit points: the trace step calls `fold_texels` only when the
scene has textures. Inside the bounce kernels (photon roulette, an eye path
through a tinted mirror or glass) the kernel branches on the material's
texture id, -1 for a constant, and calls `texel_at` only for a texture.
"""
import math

import numba as nb
import numpy as np

from dosppm_core.scene.model import LIGHT_PROJECTOR
from dosppm_core.scene.textures import CHECKERBOARD, CLAMP, MIRROR, NEAREST, REPEAT


@nb.njit(inline="always", cache=True, error_model="numpy")
def wrap_index(i, size, mode):
    """Texel index i wrapped into [0, size) as Mitsuba's wrap modes."""
    if mode == REPEAT:
        i = i % size
        return i + size if i < 0 else i
    if mode == MIRROR:
        i = i % (2 * size)
        if i < 0:
            i += 2 * size
        return 2 * size - 1 - i if i >= size else i
    return min(max(i, 0), size - 1)


@nb.njit(inline="always", cache=True, error_model="numpy")
def _floor_int(x):
    # Far outside [0, 1] (or NaN from a degenerate triangle) a float could
    # overflow the int: clamp first; every wrap mode folds it back anyway.
    if not x > -1e9:
        return -1000000000
    return int(math.floor(min(x, 1e9)))


@nb.njit(inline="always", cache=True, error_model="numpy")
def texel(info, uv_map, texels, t, s, r):
    """Linear RGB of texture t at texture coordinate (s, r)."""
    a = uv_map[t]
    u = a[0] * s + a[1] * r + a[2]
    v = a[3] * s + a[4] * r + a[5]
    off, w, h, wrap = info[t, 1], info[t, 2], info[t, 3], info[t, 5]
    if info[t, 0] == CHECKERBOARD:
        row = off if (u - math.floor(u) > 0.5) == (v - math.floor(v) > 0.5) else off + 1
        return np.float64(texels[row, 0]), np.float64(texels[row, 1]), np.float64(texels[row, 2])
    if info[t, 4] == NEAREST:
        x = wrap_index(_floor_int(u * w), w, wrap)
        y = wrap_index(_floor_int(v * h), h, wrap)
        row = off + y * w + x
        return np.float64(texels[row, 0]), np.float64(texels[row, 1]), np.float64(texels[row, 2])
    # Bilinear between the four texel centres around (u w - 1/2, v h - 1/2).
    fx, fy = u * w - 0.5, v * h - 0.5
    x0, y0 = _floor_int(fx), _floor_int(fy)
    ax, ay = fx - x0, fy - y0
    xa, xb = wrap_index(x0, w, wrap), wrap_index(x0 + 1, w, wrap)
    ya, yb = off + wrap_index(y0, h, wrap) * w, off + wrap_index(y0 + 1, h, wrap) * w
    c00, c10, c01, c11 = (1 - ax) * (1 - ay), ax * (1 - ay), (1 - ax) * ay, ax * ay
    out0 = c00 * texels[ya + xa, 0] + c10 * texels[ya + xb, 0] + c01 * texels[yb + xa, 0] + c11 * texels[yb + xb, 0]
    out1 = c00 * texels[ya + xa, 1] + c10 * texels[ya + xb, 1] + c01 * texels[yb + xa, 1] + c11 * texels[yb + xb, 1]
    out2 = c00 * texels[ya + xa, 2] + c10 * texels[ya + xb, 2] + c01 * texels[yb + xa, 2] + c11 * texels[yb + xb, 2]
    return out0, out1, out2


# Mitsuba's luminance of linear sRGB (what a bump map's height is).
LUMINANCE = (0.212671, 0.715160, 0.072169)


@nb.njit(cache=True, error_model="numpy")
def _height(texels, row):
    return (LUMINANCE[0] * texels[row, 0] + LUMINANCE[1] * texels[row, 1]
            + LUMINANCE[2] * texels[row, 2])


@nb.njit(cache=True, error_model="numpy")
def height_gradient(info, uv_map, texels, t, s, r):
    """d(height)/d(u, v) of texture t at (s, r), as Mitsuba's bitmap
    `eval_1_grad`: the derivative of the bilinear lookup of the texels'
    luminance (zero for a nearest lookup or a checkerboard), the pixel
    partials taken through the transpose of to_uv and then times the
    resolution (Mitsuba's order of the two, exact for an identity to_uv)."""
    off, w, h, wrap = info[t, 1], info[t, 2], info[t, 3], info[t, 5]
    if info[t, 0] != 0 or info[t, 4] == NEAREST:
        return 0.0, 0.0
    a = uv_map[t]
    u = a[0] * s + a[1] * r + a[2]
    v = a[3] * s + a[4] * r + a[5]
    fx, fy = u * w - 0.5, v * h - 0.5
    x0, y0 = _floor_int(fx), _floor_int(fy)
    ax, ay = fx - x0, fy - y0
    xa, xb = wrap_index(x0, w, wrap), wrap_index(x0 + 1, w, wrap)
    ya, yb = off + wrap_index(y0, h, wrap) * w, off + wrap_index(y0 + 1, h, wrap) * w
    f00, f10 = _height(texels, ya + xa), _height(texels, ya + xb)
    f01, f11 = _height(texels, yb + xa), _height(texels, yb + xb)
    dx = (1.0 - ay) * (f10 - f00) + ay * (f11 - f01)
    dy = (1.0 - ax) * (f01 - f00) + ax * (f11 - f10)
    return w * (a[0] * dx + a[3] * dy), h * (a[1] * dx + a[4] * dy)


@nb.njit(inline="always", cache=True, error_model="numpy")
def hit_uv(uvs, tris, tri, u, v):
    """The texture coordinate at barycentrics (u, v) of triangle tri."""
    t0, t1, t2 = tris[tri, 0], tris[tri, 1], tris[tri, 2]
    w = 1.0 - u - v
    s = w * uvs[t0, 0] + u * uvs[t1, 0] + v * uvs[t2, 0]
    r = w * uvs[t0, 1] + u * uvs[t1, 1] + v * uvs[t2, 1]
    return s, r


@nb.njit(inline="always", cache=True, error_model="numpy")
def texel_at(uvs, tris, tex_info, tex_uv, texels, t, tri, u, v):
    """Texture t at barycentrics (u, v) of triangle tri. The bounce kernels
    call it only when the material's texture id t >= 0, and read the
    constant row themselves otherwise: passing the texture arrays into an
    inlined helper on every bounce cost the untextured eye bounce ~3%."""
    s, r = hit_uv(uvs, tris, tri, np.float64(u), np.float64(v))
    return texel(tex_info, tex_uv, texels, t, s, r)


@nb.njit(inline="always", cache=True, error_model="numpy")
def emitter_texel(kind, axis, x_axis, cone, t, info, uv_map, texels, d0, d1, d2):
    """The texel a textured spot or projector (`scene.light_textures`;
    texture t of the light table's own arrays, `axis` and `x_axis` its
    frame, `cone` its row) sends along unit direction d; 0 behind it."""
    z = axis[0] * d0 + axis[1] * d1 + axis[2] * d2
    if not z > 0.0:
        return 0.0, 0.0, 0.0
    x = x_axis[0] * d0 + x_axis[1] * d1 + x_axis[2] * d2
    y = ((axis[1] * x_axis[2] - axis[2] * x_axis[1]) * d0 + (axis[2] * x_axis[0] - axis[0] * x_axis[2]) * d1
         + (axis[0] * x_axis[1] - axis[1] * x_axis[0]) * d2)
    if kind == LIGHT_PROJECTOR:
        return texel(info, uv_map, texels, t, 0.5 - 0.5 * x / (z * cone[0]), 0.5 - 0.5 * y / (z * cone[1]))
    k = 0.5 / (z * math.tan(cone[2]))
    return texel(info, uv_map, texels, t, 0.5 + x * k, 0.5 + y * k)


@nb.njit(inline="always", cache=True, error_model="numpy")
def triangle_texel(t, corner_uv, info, uv_map, texels, u1, u2):
    """The texel of texture t at the point of a triangle (corner uvs
    (u0, v0, u1, v1, u2, v2)) that `emit._emit_triangle` and
    `direct._point_on_triangle` pick for the numbers (u1, u2)."""
    su = math.sqrt(u1)
    b1, b2 = 1.0 - su, u2 * su
    b0 = 1.0 - b1 - b2
    s = b0 * corner_uv[0] + b1 * corner_uv[2] + b2 * corner_uv[4]
    r = b0 * corner_uv[1] + b1 * corner_uv[3] + b2 * corner_uv[5]
    return texel(info, uv_map, texels, t, s, r)


@nb.njit(cache=True, error_model="numpy")
def fold_emission(surf, prim, u, v, rgb):
    """Emission seen at hits (triangles `prim`, barycentrics u, v) times
    the texel of a textured area light there (`rgb` (n, 3), changed in
    place; `SurfaceData.emission_texture`)."""
    _fold(surf.emission_texture, surf.tri_material[prim], surf.light_tex_info, surf.light_tex_uv,
          surf.light_texels, surf, prim, u, v, rgb)


@nb.njit(cache=True, error_model="numpy")
def fold_texels(surf, prim, material, u, v, weight):
    """Hit points' weights times the texel of their textured materials
    (`material`: the hit points', which a mask or blend may have chosen
    among its parts; `weight` (n, 3) float32, changed in place; rows of
    untextured materials are left as they are)."""
    _fold(surf.mat_texture, material, surf.tex_info, surf.tex_uv, surf.texels, surf, prim, u, v, weight)


@nb.njit(cache=True, error_model="numpy")
def _fold(texture_of, material, info, uv_map, texels, surf, prim, u, v, out):
    """out[i] times the texel, in the table (info, uv_map, texels), of
    texture `texture_of[material[i]]` (-1: none, row left as it is) at
    hit i's texture coordinates."""
    for i in range(prim.shape[0]):
        t = texture_of[material[i]]
        if t < 0:
            continue
        s, r = hit_uv(surf.uvs, surf.triangles, prim[i], np.float64(u[i]), np.float64(v[i]))
        c0, c1, c2 = texel(info, uv_map, texels, t, s, r)
        out[i, 0] *= c0
        out[i, 1] *= c1
        out[i, 2] *= c2


@nb.njit(cache=True, error_model="numpy")
def lookup_many(info, uv_map, texels, t, s, r):
    """Texture t at many coordinates: (n, 3) float64 (tests, timings)."""
    out = np.empty((s.shape[0], 3))
    for i in range(s.shape[0]):
        out[i, 0], out[i, 1], out[i, 2] = texel(info, uv_map, texels, t, s[i], r[i])
    return out
