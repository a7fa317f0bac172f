"""Generation of new paths: eye rays from the camera, photons from lights."""
import math

import numba as nb
import numpy as np

from dosppm_core.kernels.bsdf import cosine_hemisphere, to_world
from dosppm_core.kernels.envmap import env_eval, env_sample
from dosppm_core.kernels.paths import offset_origin
from dosppm_core.kernels.rng import EYE_STREAM, next_float, path_state
from dosppm_core.kernels.texture import emitter_texel, triangle_texel
from dosppm_core.scene.model import (
    FILTER_BOX,
    FILTER_TENT,
    LIGHT_DIRECTIONAL,
    LIGHT_ENV,
    LIGHT_POINT,
    LIGHT_PROJECTOR,
    LIGHT_SPOT,
    LIGHT_TRIANGLE,
)

EMIT_EPS_REL = 2e-5   # the bounces' spawn offset relative to |p| (tracing.EPS_REL)


@nb.njit(cache=True, error_model="numpy")
def concentric_disk(u1, u2):
    a, b = 2.0 * u1 - 1.0, 2.0 * u2 - 1.0
    if a == 0.0 and b == 0.0:
        return 0.0, 0.0
    if abs(a) > abs(b):
        r, phi = a, (math.pi / 4.0) * (b / a)
    else:
        r, phi = b, (math.pi / 2.0) - (math.pi / 4.0) * (a / b)
    return r * math.cos(phi), r * math.sin(phi)


FILTER_RESOLUTION = 31   # Mitsuba's MI_FILTER_RESOLUTION: steps of its tabulated filter over the radius


@nb.njit(cache=True, error_model="numpy")
def filter_table(pixel_filter):
    """The filter as Mitsuba's film weighs samples with it (its
    `eval_discretized`): FILTER_RESOLUTION steps over [0, radius), step i
    holding the value at i * radius / FILTER_RESOLUTION. The tent is
    1 - |x| / radius, the Gaussian exp(-x^2 / (2 stddev^2)) minus its value
    at the radius (Mitsuba's and pbrt-v4's windowed Gaussian)."""
    kind, radius, stddev = int(pixel_filter[0]), pixel_filter[1], pixel_filter[2]
    table = np.ones(FILTER_RESOLUTION)
    bias = math.exp(-radius * radius / (2.0 * stddev * stddev))
    for i in range(FILTER_RESOLUTION):
        x = radius * i / FILTER_RESOLUTION
        if kind == FILTER_TENT:
            table[i] = 1.0 - x / radius
        elif kind != FILTER_BOX:
            table[i] = max(0.0, math.exp(-x * x / (2.0 * stddev * stddev)) - bias)
    return table


@nb.njit(cache=True, error_model="numpy")
def _step_value(table, j):
    """Value of step j of the filter over [-radius, radius] (2 n steps)."""
    n = table.shape[0]
    return table[n - 1 - j] if j < n else table[j - n]


@nb.njit(cache=True, error_model="numpy")
def _integral_to(table, radius, x):
    """Integral of the tabulated filter from -radius to x (|x| <= radius), in steps."""
    n = table.shape[0]
    t = (x + radius) * n / radius
    j = min(max(int(t), 0), 2 * n - 1)
    total = 0.0
    for k in range(j):
        total += _step_value(table, k)
    return total + _step_value(table, j) * (t - j)


@nb.njit(cache=True, error_model="numpy")
def filter_offset(table, radius, lo, hi, u):
    """An offset from the pixel centre in [lo, hi] (within [-radius,
    radius]) with density proportional to the tabulated filter, from one
    uniform u: filter importance sampling, so the eye ray's weight stays 1.
    The filter is piecewise constant, so its integral inverts exactly."""
    n = table.shape[0]
    a, b = _integral_to(table, radius, lo), _integral_to(table, radius, hi)
    target = a + u * (b - a)
    total = 0.0
    for j in range(2 * n):
        v = _step_value(table, j)
        if v > 0.0 and (total + v >= target or j == 2 * n - 1):
            x = -radius + (j + (target - total) / v) * radius / n
            return min(max(x, lo), hi)
        total += v
    return hi


@nb.njit(cache=True, error_model="numpy")
def film_position(index, size, u, pixel_filter, table, sample_border):
    """The film coordinate (pixel `index` spans [index, index + 1)) of an
    eye ray along one axis of `size` pixels: the pixel centre plus an
    offset from the filter, clipped to the film unless `sample_border`
    (Mitsuba's film only takes samples on it, and normalises each pixel by
    the weight it got). For the box of half a pixel this is index + u
    exactly (u has 24 bits), the jitter of every render before filters."""
    radius = pixel_filter[1]
    centre = index + 0.5
    lo, hi = -radius, radius
    if not sample_border:
        lo, hi = max(lo, -centre), min(hi, size - centre)
    if int(pixel_filter[0]) == FILTER_BOX:
        return centre + (lo + u * (hi - lo))
    return centre + filter_offset(table, radius, lo, hi, u)


@nb.njit(cache=True, parallel=True, error_model="numpy")
def generate_eye_rays(frame, width, seed, iteration, pixel_start, count):
    """One eye ray per pixel in [pixel_start, pixel_start + count) of
    iteration `iteration`: its film position sampled from the pixel filter
    (`film_position`) and an optional thin lens, or parallel rays for an
    orthographic camera. `frame` is `Camera.frame()`. Returns origin, direction, rng state."""
    origin = np.empty((count, 3), np.float32)
    direction = np.empty((count, 3), np.float32)
    states = np.empty(count, np.uint64)
    pos, right, up, fwd = frame[0], frame[1], frame[2], frame[3]
    tan_x, tan_y = frame[4, 0], frame[4, 1]
    aperture, focus, near = frame[5, 0], frame[5, 1], frame[5, 2]
    ortho, border = frame[6, 0] > 0.0, frame[6, 1] > 0.0
    pixel_filter = frame[7]
    table = filter_table(pixel_filter)
    job = EYE_STREAM + np.uint64(iteration)
    for i in nb.prange(count):
        pixel = pixel_start + i
        st = path_state(np.uint64(seed), job, np.uint64(pixel))
        st, ux = next_float(st)
        st, uy = next_float(st)
        col, row = pixel % width, pixel // width
        height = frame[4, 2]
        x = film_position(col, width, ux, pixel_filter, table, border)
        y = film_position(row, height, uy, pixel_filter, table, border)
        sx = (2.0 * x / width - 1.0) * tan_x
        sy = (1.0 - 2.0 * y / height) * tan_y
        d = np.empty(3)
        o = np.empty(3)
        if ortho:
            # Parallel rays from the near plane: (sx, sy) is a world offset there.
            for k in range(3):
                direction[i, k] = fwd[k]
                origin[i, k] = pos[k] + sx * right[k] + sy * up[k] + near * fwd[k]
            states[i] = st
            continue
        for k in range(3):
            d[k] = fwd[k] + sx * right[k] + sy * up[k]
            o[k] = pos[k]
        if aperture > 0.0:
            st, u1 = next_float(st)
            st, u2 = next_float(st)
            lx, ly = concentric_disk(u1, u2)
            for k in range(3):
                focus_point = pos[k] + d[k] * focus
                o[k] = pos[k] + aperture * (lx * right[k] + ly * up[k])
                d[k] = focus_point - o[k]
        inv = 1.0 / math.sqrt(d[0] * d[0] + d[1] * d[1] + d[2] * d[2])
        cos_f = (d[0] * fwd[0] + d[1] * fwd[1] + d[2] * fwd[2]) * inv
        for k in range(3):
            direction[i, k] = d[k] * inv
            origin[i, k] = o[k] + d[k] * inv * (near / cos_f)
        states[i] = st
    return origin, direction, states


@nb.njit(cache=True, error_model="numpy")
def select_light(cdf, u):
    lo, hi = 0, cdf.shape[0] - 1
    while lo < hi:
        mid = (lo + hi) // 2
        if cdf[mid] <= u:
            lo = mid + 1
        else:
            hi = mid
    return lo


@nb.njit(cache=True, parallel=True, error_model="numpy")
def emit_photons(kind, p0, p1, p2, value, cone, power, cdf, seed, jobs, starts, eps, env, light_tex):
    """Photons of the emission jobs `jobs` (rng keys), job m's photons
    being rows [starts[m], starts[m + 1]); lights chosen in proportion to
    power. A photon depends only on (seed, its job's key, its index in the
    job), so jobs emitted together or alone trace the same photons (one
    call per 1,024-photon job costs 2.5x more per photon than many jobs at
    once).

    Each photon's flux is radiant power / pdf, so the image is the sum over
    photons divided by the number emitted (eq. 5's N_e). Surface photons
    start `eps` off their light along its normal (Embree's tnear is 0).
    Photons of infinite lights start outside the scene (`_emit_infinite`;
    `env` is `kernels.envmap.env_arrays`). A textured light (`light_tex`:
    the LightTable's texture, tex_info, tex_uv, tex_texels, tri_uv) sends
    its photons as the untextured one would, each weighted by the texel of
    its direction (a spot, as Mitsuba's, or a projector) or of its point
    (a triangle). Returns origin, direction, flux, rng state, and the
    light of each.
    """
    count = starts[-1]
    origin = np.empty((count, 3), np.float32)
    direction = np.empty((count, 3), np.float32)
    flux = np.empty((count, 3), np.float32)
    states = np.empty(count, np.uint64)
    light = np.empty(count, np.int32)
    total = power.sum()
    for i in nb.prange(count):
        m = np.searchsorted(starts, i, side="right") - 1
        st = path_state(np.uint64(seed), np.uint64(jobs[m]), np.uint64(i - starts[m]))
        st, ul = next_float(st)
        st, u1 = next_float(st)
        st, u2 = next_float(st)
        st, u3 = next_float(st)
        st, u4 = next_float(st)
        li = select_light(cdf, ul)
        p_sel = power[li] / total
        if kind[li] == LIGHT_DIRECTIONAL or kind[li] == LIGHT_ENV:
            o, d, rgb = _emit_infinite(kind[li], p0[li], p1[li], cone[li, 0], value[li], env, u1, u2, u3, u4)
        else:
            o, d, rgb = _emit_finite(kind[li], p0[li], p1[li], p2[li], value[li], cone[li], light_tex, li,
                                     u1, u2, u3, u4, eps)
        for k in range(3):
            origin[i, k] = o[k]
            direction[i, k] = d[k]
            flux[i, k] = rgb[k] / p_sel
        states[i] = st
        light[i] = li
    return origin, direction, flux, states, light


@nb.njit(inline="always", cache=True, error_model="numpy")
def _emit_finite(kind, p0, p1, p2, value, cone, light_tex, li, u1, u2, u3, u4, eps):
    """A photon of a triangle, point, spot or projector light (row li):
    origin, direction and flux / pdf (RGB)."""
    if kind == LIGHT_TRIANGLE:
        o, d, scale = _emit_triangle(p0, p1, p2, u1, u2, u3, u4, eps)
    elif kind == LIGHT_POINT:
        o, d, scale = _emit_point(p0, u1, u2)
    elif kind == LIGHT_SPOT:
        o, d, scale = _emit_spot(p0, p1, cone, u1, u2)
    else:
        o, d, scale = _emit_projector(p0, p1, p2, cone, u1, u2)
    c0, c1, c2 = _texel_weight(kind, p1, p2, cone, light_tex, li, d, u1, u2)
    return o, d, (value[0] * scale * c0, value[1] * scale * c1, value[2] * scale * c2)


@nb.njit(inline="always", cache=True, error_model="numpy")
def _texel_weight(kind, axis, x_axis, cone, light_tex, li, d, u1, u2):
    """What a photon of light li (direction d, drawn from u1, u2) is
    weighted by: 1, or the texel of a textured light (`emit_photons`)."""
    t = light_tex[0][li]
    if t < 0:
        return 1.0, 1.0, 1.0
    if kind == LIGHT_TRIANGLE:
        return triangle_texel(t, light_tex[4][li], light_tex[1], light_tex[2], light_tex[3], u1, u2)
    return emitter_texel(kind, axis, x_axis, cone, t, light_tex[1], light_tex[2], light_tex[3], d[0], d[1], d[2])


@nb.njit(cache=True, error_model="numpy")
def _emit_point(pos, u1, u2):
    """A uniform direction: flux / pdf = 4 pi I."""
    z = 1.0 - 2.0 * u1
    r = math.sqrt(max(0.0, 1.0 - z * z))
    phi = 2.0 * math.pi * u2
    return (pos[0], pos[1], pos[2]), (r * math.cos(phi), r * math.sin(phi), z), 4.0 * math.pi


@nb.njit(cache=True, error_model="numpy")
def _emit_triangle(a, b, c, u1, u2, u3, u4, eps):
    """Uniform point, cosine direction about the CCW normal. Returns the
    factor pi * area that turns radiance into flux / pdf."""
    su = math.sqrt(u1)
    ba, bb = 1.0 - su, u2 * su
    e1 = (b[0] - a[0], b[1] - a[1], b[2] - a[2])
    e2 = (c[0] - a[0], c[1] - a[1], c[2] - a[2])
    nx = e1[1] * e2[2] - e1[2] * e2[1]
    ny = e1[2] * e2[0] - e1[0] * e2[2]
    nz = e1[0] * e2[1] - e1[1] * e2[0]
    nl = math.sqrt(nx * nx + ny * ny + nz * nz)
    nx, ny, nz = nx / nl, ny / nl, nz / nl
    x, y, z = cosine_hemisphere(u3, u4)
    d = to_world(x, y, z, nx, ny, nz)
    px, py, pz = a[0] + ba * e1[0] + bb * e2[0], a[1] + ba * e1[1] + bb * e2[1], a[2] + ba * e1[2] + bb * e2[2]
    # Off the light like a bounce (relative to |p|): a fixed offset vanishes
    # in float32 far from the origin, and every photon would hit the
    # light's own back (measured: all of them at 1e5 mm).
    o = offset_origin(px, py, pz, nx, ny, nz, nx, ny, nz, EMIT_EPS_REL, eps)
    return o, d, math.pi * 0.5 * nl


@nb.njit(cache=True, error_model="numpy")
def _emit_spot(pos, axis, cone, u1, u2):
    """Uniform direction in the cutoff cone, weighted by Mitsuba's falloff
    (1 inside the beam, linear in angle to 0 at the cutoff)."""
    cos_cut, cutoff, beam = cone[0], cone[2], cone[3]
    z = 1.0 - u1 * (1.0 - cos_cut)
    r = math.sqrt(max(0.0, 1.0 - z * z))
    phi = 2.0 * math.pi * u2
    d = to_world(r * math.cos(phi), r * math.sin(phi), z, axis[0], axis[1], axis[2])
    theta = math.acos(min(1.0, z))
    fall = 1.0 if theta <= beam else max(0.0, (cutoff - theta) / (cutoff - beam))
    return (pos[0], pos[1], pos[2]), d, fall * 2.0 * math.pi * (1.0 - cos_cut)


@nb.njit(cache=True, error_model="numpy")
def _emit_infinite(kind, axis, centre, radius, value, env, u1, u2, u3, u4):
    """A photon of a directional light (travelling along `axis`) or of
    the environment (arriving from a direction w drawn by luminance,
    pdf p): it leaves a uniform point of the disc of the bounding sphere's
    radius R facing w, a plane tangent to the sphere outside it, along -w.
    Every point of the scene then receives these photons at the density
    that parallel light of its direction has, so flux = pi R^2 E, or
    pi R^2 L(w) / p. Returns origin, direction, flux (RGB)."""
    if kind == LIGHT_DIRECTIONAL:
        w0, w1, w2 = -axis[0], -axis[1], -axis[2]
        l0, l1, l2, pdf = value[0], value[1], value[2], 1.0
    else:
        w0, w1, w2, pdf = env_sample(env, u1, u2)
        l0, l1, l2 = env_eval(env, w0, w1, w2)
    disc = math.pi * radius * radius
    if not pdf > 0.0:
        pdf, disc = 1.0, 0.0
    dx, dy = concentric_disk(u3, u4)
    x0, x1, x2 = to_world(dx, dy, 1.0, w0, w1, w2)      # the disc point, lifted by R along w
    o = (centre[0] + radius * x0, centre[1] + radius * x1, centre[2] + radius * x2)
    return o, (-w0, -w1, -w2), (l0 * disc / pdf, l1 * disc / pdf, l2 * disc / pdf)


@nb.njit(cache=True, error_model="numpy")
def _emit_projector(pos, axis, x_axis, cone, u1, u2):
    """Through a uniform point of the projector's image plane at distance
    1 (its irradiance is constant there): flux / pdf = pi E x the plane's
    area, as Mitsuba's sample_ray."""
    x, y = (2.0 * u1 - 1.0) * cone[0], (2.0 * u2 - 1.0) * cone[1]
    y0 = axis[1] * x_axis[2] - axis[2] * x_axis[1]
    y1 = axis[2] * x_axis[0] - axis[0] * x_axis[2]
    y2 = axis[0] * x_axis[1] - axis[1] * x_axis[0]
    d0 = axis[0] + x * x_axis[0] + y * y0
    d1 = axis[1] + x * x_axis[1] + y * y1
    d2 = axis[2] + x * x_axis[2] + y * y2
    dl = math.sqrt(d0 * d0 + d1 * d1 + d2 * d2)
    return (pos[0], pos[1], pos[2]), (d0 / dl, d1 / dl, d2 / dl), 4.0 * math.pi * cone[0] * cone[1]
