"""Direct light at hit points by next-event estimation: one light sample,
and the shadow ray that tests it, per hit point and eye iteration.

At a hit point x (normal n facing the eye, wo toward the eye, camera
weight W, material m) a light is chosen by power, a point y on it sampled,
and the unoccluded contribution

    W * reflectance_m * f(wo, wi) * cos(n, wi) * Le(y -> x) * G(x, y) / pdf

written beside a shadow ray from x to y. The ray's pixel receives the
contribution if nothing lies between x and y. Triangle lights are sampled
by area (G = cos_y / d^2), point and spot lights have G = 1 / d^2.

The light choice and the point on the light draw from the eye path's own
random stream at the hit point, so the same seed samples the same light
whatever chunk or tracer the hit point was found in.
"""
import math

import numba as nb
import numpy as np

from dosppm_core.kernels.bsdf import eval_bsdf
from dosppm_core.kernels.emit import select_light
from dosppm_core.kernels.paths import offset_origin
from dosppm_core.kernels.rng import next_float
from dosppm_core.scene.model import LIGHT_POINT, LIGHT_TRIANGLE


@nb.njit(inline="always", cache=True, error_model="numpy")
def _point_on_triangle(a, b, c, u1, u2):
    """A uniform point on triangle abc, its unit CCW normal and its area."""
    su = math.sqrt(u1)
    ba, bb = 1.0 - su, u2 * su
    e10, e11, e12 = b[0] - a[0], b[1] - a[1], b[2] - a[2]
    e20, e21, e22 = c[0] - a[0], c[1] - a[1], c[2] - a[2]
    nx = e11 * e22 - e12 * e21
    ny = e12 * e20 - e10 * e22
    nz = e10 * e21 - e11 * e20
    nl = math.sqrt(nx * nx + ny * ny + nz * nz)
    q0 = a[0] + ba * e10 + bb * e20
    q1 = a[1] + ba * e11 + bb * e21
    q2 = a[2] + ba * e12 + bb * e22
    return q0, q1, q2, nx / nl, ny / nl, nz / nl, 0.5 * nl


@nb.njit(inline="always", cache=True, error_model="numpy")
def spot_falloff(cone, cos_t):
    """Mitsuba's spot profile (as `emit._emit_spot`): 1 inside the beam,
    linear in angle to 0 at the cutoff."""
    if cos_t <= cone[0]:
        return 0.0
    theta = math.acos(min(1.0, cos_t))
    if theta <= cone[3]:
        return 1.0
    return max(0.0, (cone[2] - theta) / (cone[2] - cone[3]))


@nb.njit(inline="always", cache=True, error_model="numpy")
def _sample_light(lights, li, p0, p1, p2, u1, u2):
    """A point y on light li seen from x = p: (y, unit wi from x to y,
    distance, the light's Le * G factor per colour channel scale (a scalar
    times `value`), and whether y lies on a surface (a triangle light))."""
    kind, lp0, lp1, lp2, value, cone, _power, _cdf = lights
    if kind[li] == LIGHT_TRIANGLE:
        q0, q1, q2, m0, m1, m2, area = _point_on_triangle(lp0[li], lp1[li], lp2[li], u1, u2)
    else:
        q0, q1, q2 = lp0[li, 0], lp0[li, 1], lp0[li, 2]
        m0 = m1 = m2 = area = 0.0
    d0, d1, d2 = q0 - p0, q1 - p1, q2 - p2
    dist2 = d0 * d0 + d1 * d1 + d2 * d2
    if not dist2 > 0.0:
        return q0, q1, q2, 0.0, 0.0, 0.0, 0.0, 0.0
    dist = math.sqrt(dist2)
    w0, w1, w2 = d0 / dist, d1 / dist, d2 / dist
    if kind[li] == LIGHT_TRIANGLE:
        cos_y = -(m0 * w0 + m1 * w1 + m2 * w2)    # one-sided: emits on its CCW front
        g = cos_y * area / dist2 if cos_y > 0.0 else 0.0
    elif kind[li] == LIGHT_POINT:
        g = 1.0 / dist2
    else:
        axis = lp1[li]
        g = spot_falloff(cone[li], -(axis[0] * w0 + axis[1] * w1 + axis[2] * w2)) / dist2
    return q0, q1, q2, w0, w1, w2, dist, g


@nb.njit(cache=True, parallel=True, error_model="numpy")
def sample_direct(hits, states, surf, lights, eps_rel):
    """One light sample per hit point. `hits` is (position, normal,
    outgoing, weight, material) of `jobs.HitPoints`, `states` each eye
    path's rng state at its hit point, `surf` a `SurfaceData`, `lights`
    the LightTable's (kind, p0, p1, p2, value, cone, power, cdf).

    Returns (rows, origin, direction, tmax, radiance) of the shadow rays
    with a non-zero contribution (`rows` index the hit points)."""
    position, normal, outgoing, weight, material = hits
    kinds, refl, rough, eps_abs = surf.kind, surf.reflectance, surf.roughness, surf.eps_abs
    power, cdf = lights[6], lights[7]
    total = power.sum()
    n = position.shape[0]
    origin = np.empty((n, 3), np.float32)
    direction = np.empty((n, 3), np.float32)
    tmax = np.empty(n, np.float32)
    radiance = np.zeros((n, 3), np.float32)
    keep = np.zeros(n, np.bool_)
    for i in nb.prange(n):
        st, ul = next_float(states[i])
        st, u1 = next_float(st)
        st, u2 = next_float(st)
        li = select_light(cdf, ul)
        p0, p1, p2 = np.float64(position[i, 0]), np.float64(position[i, 1]), np.float64(position[i, 2])
        q0, q1, q2, w0, w1, w2, dist, g = _sample_light(lights, li, p0, p1, p2, u1, u2)
        if not g > 0.0:
            continue
        n0, n1, n2 = normal[i, 0], normal[i, 1], normal[i, 2]
        m = material[i]
        f = eval_bsdf(kinds[m], np.float64(rough[m]), n0, n1, n2,
                      outgoing[i, 0], outgoing[i, 1], outgoing[i, 2], w0, w1, w2)
        cos_x = n0 * w0 + n1 * w1 + n2 * w2
        scale = f * cos_x * g * total / power[li]
        if not scale > 0.0:
            continue
        o0, o1, o2 = offset_origin(p0, p1, p2, n0, n1, n2, w0, w1, w2, eps_rel, eps_abs)
        # Stop short of the light: a triangle light must not shadow itself.
        end = eps_rel * max(abs(q0), abs(q1), abs(q2)) + eps_abs
        t = math.sqrt((q0 - o0) ** 2 + (q1 - o1) ** 2 + (q2 - o2) ** 2) - 2.0 * end
        if not t > 0.0:
            continue
        origin[i, 0], origin[i, 1], origin[i, 2] = o0, o1, o2
        direction[i, 0], direction[i, 1], direction[i, 2] = w0, w1, w2
        tmax[i] = t
        for k in range(3):
            radiance[i, k] = weight[i, k] * refl[m, k] * lights[4][li, k] * scale
        keep[i] = True
    rows = np.flatnonzero(keep)
    return rows, origin[rows], direction[rows], tmax[rows], radiance[rows]
