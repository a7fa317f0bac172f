"""The environment light in the kernels: its radiance in a direction,
and directions sampled by luminance with their solid-angle pdf.

`env` is the tuple (texels, to_world, row cdf, column cdfs, patch pdf)
of `env_arrays`; the layout and the tables are `scene.envmap`'s. A
direction d (world, pointing away from the scene) is looked up in the
map's frame as v = to_world^T d, as Mitsuba's envmap does.
"""
import math

import numba as nb
import numpy as np


def env_arrays(lights) -> tuple:
    """The kernels' tuple for a `LightTable`'s environment (a black map
    when it has none)."""
    row_cdf, col_cdf, pdf = lights.env_distribution()
    return (lights.env_texels, np.ascontiguousarray(lights.env_to_world, np.float64), row_cdf, col_cdf, pdf)


@nb.njit(inline="always", cache=True, error_model="numpy")
def _local_uv(env, d0, d1, d2):
    """(u, v) of world direction d: u = phi / 2 pi, v = theta / pi."""
    r = env[1]
    x = r[0, 0] * d0 + r[1, 0] * d1 + r[2, 0] * d2
    y = r[0, 1] * d0 + r[1, 1] * d1 + r[2, 1] * d2
    z = r[0, 2] * d0 + r[1, 2] * d1 + r[2, 2] * d2
    n = math.sqrt(x * x + y * y + z * z)
    u = math.atan2(x, -z) / (2.0 * math.pi)
    v = math.acos(max(-1.0, min(1.0, y / n))) / math.pi
    return u, v


@nb.njit(cache=True, error_model="numpy")
def env_eval(env, d0, d1, d2):
    """The radiance (r, g, b) arriving from direction d: Mitsuba's
    bilinear lookup (half a texel's shift in u, the wrap column)."""
    tex = env[0]
    h, w = tex.shape[0], tex.shape[1] - 1
    u, v = _local_uv(env, d0, d1, d2)
    u -= 0.5 / w
    u -= math.floor(u)
    v -= math.floor(v)
    x, y = u * w, v * (h - 1)
    px, py = min(int(x), w - 1), min(int(y), h - 2)
    fx, fy = x - px, y - py
    out = np.empty(3)
    for k in range(3):
        a = (1.0 - fx) * tex[py, px, k] + fx * tex[py, px + 1, k]
        b = (1.0 - fx) * tex[py + 1, px, k] + fx * tex[py + 1, px + 1, k]
        out[k] = (1.0 - fy) * a + fy * b
    return out[0], out[1], out[2]


@nb.njit(cache=True, error_model="numpy")
def env_pdf(env, d0, d1, d2):
    """The solid-angle density with which `env_sample` returns d."""
    pdf = env[4]
    h1, w = pdf.shape[0], pdf.shape[1]
    u, v = _local_uv(env, d0, d1, d2)
    u -= 0.5 / w
    u -= math.floor(u)
    return pdf[min(int(v * h1), h1 - 1), min(int(u * w), w - 1)]


@nb.njit(inline="always", cache=True, error_model="numpy")
def _pick(cdf, u):
    """The interval i of a cdf (cdf[0] = 0 .. cdf[n] = 1) holding u, and u
    rescaled to [0, 1) within it."""
    lo, hi = 0, cdf.shape[0] - 2
    while lo < hi:
        mid = (lo + hi + 1) // 2
        if cdf[mid] <= u:
            lo = mid
        else:
            hi = mid - 1
    width = cdf[lo + 1] - cdf[lo]
    return lo, min(max((u - cdf[lo]) / width, 0.0), 0.9999999999999999) if width > 0.0 else 0.5


@nb.njit(cache=True, error_model="numpy")
def env_sample(env, u1, u2):
    """A world direction (away from the scene) drawn by the map's
    luminance: a patch row, a patch in it, then a uniform point of the
    patch in solid angle. Returns (d0, d1, d2, pdf); pdf 0 for a black map."""
    row_cdf, col_cdf, pdf = env[2], env[3], env[4]
    h1, w = pdf.shape[0], pdf.shape[1]
    i, su = _pick(row_cdf, u1)
    j, sv = _pick(col_cdf[i], u2)
    c0, c1 = math.cos(i * math.pi / h1), math.cos((i + 1) * math.pi / h1)
    cos_t = c0 - su * (c0 - c1)
    sin_t = math.sqrt(max(0.0, 1.0 - cos_t * cos_t))
    phi = 2.0 * math.pi * (j + 0.5 + sv) / w
    x, y, z = math.sin(phi) * sin_t, cos_t, -math.cos(phi) * sin_t
    r = env[1]
    d0 = r[0, 0] * x + r[0, 1] * y + r[0, 2] * z
    d1 = r[1, 0] * x + r[1, 1] * y + r[1, 2] * z
    d2 = r[2, 0] * x + r[2, 1] * y + r[2, 2] * z
    return d0, d1, d2, pdf[i, j]


@nb.njit(cache=True, error_model="numpy")
def escaped_radiance(env, direction, weight):
    """weight * the radiance arriving along each direction (n, 3): what
    eye rays that leave the scene see."""
    n = direction.shape[0]
    out = np.empty((n, 3), np.float32)
    for i in range(n):
        r, g, b = env_eval(env, np.float64(direction[i, 0]), np.float64(direction[i, 1]),
                           np.float64(direction[i, 2]))
        out[i, 0], out[i, 1], out[i, 2] = weight[i, 0] * r, weight[i, 1] * g, weight[i, 2] * b
    return out


@nb.njit(cache=True, error_model="numpy")
def escaped_mis_radiance(env, direction, radiance, pdf, c_light, p_select):
    """What BSDF-sampled direct-light rays (`kernels.direct._bsdf_ray`)
    that leave the scene bring: radiance * Le / (c_light p_select
    p_env + pdf), the balance heuristic against sampling the map."""
    n = direction.shape[0]
    out = np.empty((n, 3), np.float32)
    for i in range(n):
        d0, d1, d2 = np.float64(direction[i, 0]), np.float64(direction[i, 1]), np.float64(direction[i, 2])
        r, g, b = env_eval(env, d0, d1, d2)
        k = 1.0 / (c_light * p_select * env_pdf(env, d0, d1, d2) + pdf[i])
        out[i, 0], out[i, 1], out[i, 2] = radiance[i, 0] * r * k, radiance[i, 1] * g * k, radiance[i, 2] * b * k
    return out
