"""Direct light at hit points by next-event estimation: one light sample,
and the shadow ray that tests it, per hit point and eye iteration.

At a hit point x (normal n facing the eye, wo toward the eye, camera
weight W, material m) a light is chosen by power, a point y on it sampled,
and the unoccluded contribution

    W * reflectance_m * f(wo, wi) * cos(n, wi) * Le(y -> x) * G(x, y) / pdf

written beside a shadow ray from x to y. The ray's pixel receives the
contribution if nothing lies between x and y. Triangle lights are sampled
by area (G = cos_y / d^2), point and spot lights have G = 1 / d^2.

On a glossy hit point in a scene with triangle lights, a narrow lobe
reflecting a large light is sampled badly by the light alone, so the ray
is chosen by one-sample multiple importance sampling (Veach 1997, 9.2.4):
with probability C_LIGHT the light sample above, else a direction from the
BSDF; either way the estimate is f cos Le / (C_LIGHT p_light + C_BSDF
p_bsdf) in solid angle, the balance heuristic. A BSDF-sampled ray looks for
its first hit (`tmax` FIRST_HIT); if that is the front of an emitting
triangle, `emitter_radiance` finishes the estimate there. One ray per hit
point either way, so an eye path stays one path (exact accounting). Point
and spot lights are sampled by the light alone (no direction finds them).

Among many lights, power alone is a poor guide: most of a building's 600
lamps are far from any one hit point, or behind its walls. So elsewhere
the light is chosen from a defensive mixture of the light tree
(`light_tree`: bounds on what each group of lights can deliver to the hit
point, O(log n)) and the lights its cell learned from the photons' first
hits (`light_cache`: which lights reach there, walls included); the
estimate divides by the mixture's probability of the light chosen, which
is positive for every light that can light the hit point. Glossy hit points
under triangle lights keep power alone: the one-sample MIS above needs
the light technique's pdf where a BSDF-sampled ray finds an emitter.

Infinite lights (directional, environment) have no place in the tree: a
fixed share of the choices (`trace._infinite_arrays`: all of them when
every light is infinite, half when the scene has both) picks among them by
power, and the estimate divides by the whole mixture's probability. A
directional light is a delta light (a shadow ray toward it, past the
scene's bounding sphere); the environment is sampled by its luminance
(`kernels.envmap`), and on glossy hit points takes part in the MIS above
like a triangle light: a BSDF-sampled ray that leaves the scene finds it
(`kernels.envmap.escaped_mis_radiance`).

The light choice and the point on the light draw from the eye path's own
random stream at the hit point, so the same seed samples the same light
whatever chunk or tracer the hit point was found in.
"""
import math

import numba as nb
import numpy as np

from dosppm_core.kernels.bsdf import eval_bsdf, glossy_pdf, sample_bsdf
from dosppm_core.kernels.emit import select_light
from dosppm_core.kernels.envmap import env_eval, env_sample
from dosppm_core.kernels.light_cache import cell_pmf, pick_in_cell, read_cell
from dosppm_core.kernels.light_tree import sample_tree, tree_pmf
from dosppm_core.kernels.anisotropic import hp_eval, hp_pdf, hp_sample
from dosppm_core.kernels.materials import is_coloured
from dosppm_core.kernels.paths import offset_origin
from dosppm_core.kernels.rng import next_float
from dosppm_core.kernels.texture import emitter_texel, triangle_texel
from dosppm_core.scene.model import GLOSSY, LIGHT_DIRECTIONAL, LIGHT_ENV, LIGHT_POINT, LIGHT_PROJECTOR, LIGHT_TRIANGLE

C_LIGHT = 0.5          # share of light samples at glossy hit points (MIS); 1 elsewhere
FIRST_HIT = 1e37       # tmax of a BSDF-sampled ray: finite (the wire refuses inf), past any scene


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
def projector_profile(axis, x_axis, cone, v0, v1, v2):
    """A projector's intensity over its irradiance in unit direction v:
    pi / cos^3 inside its frustum (a constant image plane at distance 1
    gets pi E, as in Mitsuba), 0 outside."""
    cz = axis[0] * v0 + axis[1] * v1 + axis[2] * v2
    if not cz > 0.0:
        return 0.0
    y0 = axis[1] * x_axis[2] - axis[2] * x_axis[1]
    y1 = axis[2] * x_axis[0] - axis[0] * x_axis[2]
    y2 = axis[0] * x_axis[1] - axis[1] * x_axis[0]
    x = (x_axis[0] * v0 + x_axis[1] * v1 + x_axis[2] * v2) / cz
    y = (y0 * v0 + y1 * v1 + y2 * v2) / cz
    if abs(x) > cone[0] or abs(y) > cone[1]:
        return 0.0
    return math.pi / (cz * cz * cz)


@nb.njit(inline="always", cache=True, error_model="numpy")
def _sample_light(lights, li, p0, p1, p2, u1, u2):
    """A point y on light li seen from x = p: (y, unit wi from x to y,
    distance, the light's Le * G factor per colour channel scale (a scalar
    times `value`), and whether y lies on a surface (a triangle light))."""
    kind, lp0, lp1, lp2, cone = lights[0], lights[1], lights[2], lights[3], lights[5]
    if kind[li] == LIGHT_DIRECTIONAL:
        w0, w1, w2 = -lp0[li, 0], -lp0[li, 1], -lp0[li, 2]
        dist = _beyond_sphere(lp1[li], cone[li, 0], p0, p1, p2)
        return p0 + dist * w0, p1 + dist * w1, p2 + dist * w2, w0, w1, w2, dist, 1.0
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
    elif kind[li] == LIGHT_PROJECTOR:
        g = projector_profile(lp1[li], lp2[li], cone[li], -w0, -w1, -w2) / dist2
    else:
        axis = lp1[li]
        g = spot_falloff(cone[li], -(axis[0] * w0 + axis[1] * w1 + axis[2] * w2)) / dist2
    return q0, q1, q2, w0, w1, w2, dist, g


@nb.njit(cache=True, error_model="numpy")
def light_le(lights, li, w0, w1, w2, u1, u2):
    """What light li sends toward a hit point that sees it along unit w,
    per unit of `_sample_light`'s g (for the numbers u1, u2): its `value`,
    times the texel of the direction -w for a textured spot or projector,
    or of the point sampled on a textured triangle (lights[14:19],
    `trace.light_textures`). A call, not inlined: inlining it (and the
    texel lookups it inlines) into every shadow-ray path multiplied the
    kernel's IR until one compile took minutes and gigabytes."""
    value, t = lights[4], lights[14][li]
    if t < 0:
        return value[li, 0], value[li, 1], value[li, 2]
    if lights[0][li] == LIGHT_TRIANGLE:
        c0, c1, c2 = triangle_texel(t, lights[18][li], lights[15], lights[16], lights[17], u1, u2)
    else:
        c0, c1, c2 = emitter_texel(lights[0][li], lights[2][li], lights[3][li], lights[5][li], t,
                                   lights[15], lights[16], lights[17], -w0, -w1, -w2)
    return value[li, 0] * c0, value[li, 1] * c1, value[li, 2] * c2


@nb.njit(inline="always", cache=True, error_model="numpy")
def _light_value(lights, li, w0, w1, w2, u1, u2):
    """`light_le`, with an untextured light's value read here: the call
    passes the whole light tuple, and made every shadow ray a third dearer
    when it was made for every light."""
    if lights[14][li] < 0:
        value = lights[4]
        return value[li, 0], value[li, 1], value[li, 2]
    return light_le(lights, li, w0, w1, w2, u1, u2)


@nb.njit(inline="always", cache=True, error_model="numpy")
def _beyond_sphere(centre, radius, p0, p1, p2):
    """How far a shadow ray toward an infinite light runs from p: past the
    scene's bounding sphere, wherever p is (Mitsuba's 2 max(R, |p - c|))."""
    d0, d1, d2 = p0 - centre[0], p1 - centre[1], p2 - centre[2]
    return 2.0 * max(radius, math.sqrt(d0 * d0 + d1 * d1 + d2 * d2))


@nb.njit(cache=True, parallel=True, error_model="numpy")
def sample_direct(hits, states, surf, extras, lights, cache, infinite, mis, eps_rel):
    """One direct-light ray per hit point. `hits` is (position, normal,
    outgoing, weight, material) of `jobs.HitPoints` and the frames of
    anisotropic hit points (`anisotropic.hit_point_frames`, (0, 5) in a
    scene without them), `states` each eye
    path's rng state at its hit point, `surf` a `SurfaceData`, `lights`
    the LightTable's (kind, p0, p1, p2, value, cone, power, cdf) and its
    light tree's arrays, `cache` the light cache's arrays (frozen: no
    photon writes them meanwhile), `infinite` (cdf by power over the
    infinite lights, their share of the choices, then the environment's
    `kernels.envmap.env_arrays`), `mis` whether the scene has triangle
    lights or an environment (glossy hit points then use MIS). `extras` is
    `surf.material_extras`: None, and numba compiles the loop without the
    coloured kinds' branch, as the bounces do (measured alone, on the
    built-in scene, this and `infinite` None changed nothing; the 40% the
    plain kinds' rays had lost was `light_le`'s call, see `_light_value`).

    Returns (rows, origin, direction, tmax, radiance, pdf) of the rays that
    may contribute (`rows` index the hit points; `jobs.ShadowRays`).
    (`sample_direct_serial`: the same on one thread, for small batches.)"""
    n = hits[0].shape[0]
    out, keep = _direct_buffers(n)
    total = lights[6].sum()     # once, not per ray: hundreds of lights in some scenes
    for i in nb.prange(n):
        keep[i] = _direct_ray(i, hits, states, surf, extras, lights, cache, infinite, mis, eps_rel, total,
                              out)
    return _kept_rays(out, keep)


@nb.njit(cache=True, error_model="numpy")
def sample_direct_serial(hits, states, surf, extras, lights, cache, infinite, mis, eps_rel):
    """`sample_direct` on this thread."""
    n = hits[0].shape[0]
    out, keep = _direct_buffers(n)
    total = lights[6].sum()
    for i in range(n):
        keep[i] = _direct_ray(i, hits, states, surf, extras, lights, cache, infinite, mis, eps_rel, total,
                              out)
    return _kept_rays(out, keep)


@nb.njit(cache=True, error_model="numpy")
def _direct_buffers(n):
    out = (np.empty((n, 3), np.float32), np.empty((n, 3), np.float32), np.empty(n, np.float32),
           np.zeros((n, 3), np.float32), np.zeros(n, np.float32))
    return out, np.zeros(n, np.bool_)


@nb.njit(cache=True, error_model="numpy")
def _kept_rays(out, keep):
    rows = np.flatnonzero(keep)
    origin, direction, tmax, radiance, pdf = out
    return rows, origin[rows], direction[rows], tmax[rows], radiance[rows], pdf[rows]


@nb.njit(inline="always", cache=True, error_model="numpy")
def _direct_ray(i, hits, states, surf, extras, lights, cache, infinite, mis, eps_rel, total, out):
    """Hit point i's ray into row i of `out`; whether it may contribute."""
    position, normal, outgoing, weight, material, frames = hits
    m = material[i]
    glossy = mis and surf.kind[m] == GLOSSY
    st, ul = next_float(states[i])
    st, u1 = next_float(st)
    st, u2 = next_float(st)
    p0, p1, p2 = np.float64(position[i, 0]), np.float64(position[i, 1]), np.float64(position[i, 2])
    n0, n1, n2 = normal[i, 0], normal[i, 1], normal[i, 2]
    o0, o1, o2 = outgoing[i, 0], outgoing[i, 1], outgoing[i, 2]
    if extras is not None and is_coloured(surf.kind[m]):
        st, ut = next_float(st)
        return _coloured_ray(i, p0, p1, p2, n0, n1, n2, o0, o1, o2, weight, m, surf, lights, infinite, total,
                             mis, ut, ul, u1, u2, eps_rel, out, frames)
    if glossy:
        st, ut = next_float(st)
        if ut >= C_LIGHT:
            return _bsdf_ray(i, p0, p1, p2, n0, n1, n2, o0, o1, o2, weight, m, surf, u1, u2, eps_rel, out)
        return _light_ray(i, p0, p1, p2, n0, n1, n2, o0, o1, o2, weight, m, surf, lights,
                          infinite, total, glossy, ul, u1, u2, eps_rel, out)
    return _chosen_light_ray(i, p0, p1, p2, n0, n1, n2, o0, o1, o2, weight, m, surf, lights,
                             cache, infinite, st, ul, u1, u2, eps_rel, out)


@nb.njit(inline="always", cache=True, error_model="numpy")
def _aim(i, out, p0, p1, p2, n0, n1, n2, w0, w1, w2, q0, q1, q2, eps_rel, eps_abs):
    """Row i's shadow ray: from hit point p, spawned off its surface toward
    w, to light point q, stopping short of q (a triangle light must not
    shadow itself). Aimed from the spawned origin: from p, a ray lifted off
    a floor by the spawn offset ran on past the lamp it was aimed at when
    it rose at less than ~60 degrees, and the lamp shadowed itself (the
    generated building's floor was 10% dark). False: no room for a ray."""
    origin, direction, tmax = out[0], out[1], out[2]
    s0, s1, s2 = offset_origin(p0, p1, p2, n0, n1, n2, w0, w1, w2, eps_rel, eps_abs)
    d0, d1, d2 = q0 - s0, q1 - s1, q2 - s2
    dist = math.sqrt(d0 * d0 + d1 * d1 + d2 * d2)
    t = dist - 2.0 * (eps_rel * max(abs(q0), abs(q1), abs(q2)) + eps_abs)
    if not t > 0.0:
        return False
    origin[i, 0], origin[i, 1], origin[i, 2] = s0, s1, s2
    direction[i, 0], direction[i, 1], direction[i, 2] = d0 / dist, d1 / dist, d2 / dist
    tmax[i] = t
    out[4][i] = 0.0
    return True


@nb.njit(inline="always", cache=True, error_model="numpy")
def _write_radiance(i, out, scale, weight, refl, m, l0, l1, l2):
    """Row i's contribution if unoccluded: W refl scale Le (per channel)."""
    out[3][i, 0] = weight[i, 0] * refl[m, 0] * scale * l0
    out[3][i, 1] = weight[i, 1] * refl[m, 1] * scale * l1
    out[3][i, 2] = weight[i, 2] * refl[m, 2] * scale * l2


@nb.njit(inline="always", cache=True, error_model="numpy")
def _write_ray(i, out, p0, p1, p2, n0, n1, n2, w0, w1, w2, t, scale, weight, refl, m, pdf,
               eps_rel, eps_abs):
    origin, direction, tmax, radiance, pdfs = out
    origin[i, 0], origin[i, 1], origin[i, 2] = offset_origin(p0, p1, p2, n0, n1, n2, w0, w1, w2,
                                                             eps_rel, eps_abs)
    direction[i, 0], direction[i, 1], direction[i, 2] = w0, w1, w2
    tmax[i] = t
    pdfs[i] = pdf
    for k in range(3):
        radiance[i, k] = weight[i, k] * refl[m, k] * scale


@nb.njit(inline="always", cache=True, error_model="numpy")
def _light_ray(i, p0, p1, p2, n0, n1, n2, o0, o1, o2, weight, m, surf, lights, infinite, total, glossy,
               ul, u1, u2, eps_rel, out):
    """A shadow ray to a point sampled on a light chosen by power; writes
    row i of `out`, returns whether it may contribute."""
    power, cdf = lights[6], lights[7]
    li = select_light(cdf, ul)
    p_sel = power[li] / total
    if infinite is not None and lights[0][li] == LIGHT_ENV:
        return _env_ray(i, p0, p1, p2, n0, n1, n2, o0, o1, o2, weight, m, surf, lights, infinite, li,
                        p_sel, glossy, u1, u2, eps_rel, out)
    q0, q1, q2, w0, w1, w2, dist, g = _sample_light(lights, li, p0, p1, p2, u1, u2)
    if not g > 0.0:
        return False
    alpha = np.float64(surf.roughness[m])
    f = eval_bsdf(surf.kind[m], alpha, n0, n1, n2, o0, o1, o2, w0, w1, w2)
    cos_x = n0 * w0 + n1 * w1 + n2 * w2
    if not f * cos_x > 0.0:
        return False
    if glossy and lights[0][li] == LIGHT_TRIANGLE:
        # One-sample MIS, balance heuristic: f cos Le / (c_l p_l + c_b p_b).
        p_light = p_sel / g
        p_bsdf = glossy_pdf(alpha, n0, n1, n2, o0, o1, o2, w0, w1, w2)
        scale = f * cos_x / (C_LIGHT * p_light + (1.0 - C_LIGHT) * p_bsdf)
    elif glossy:
        scale = f * cos_x * g / (p_sel * C_LIGHT)   # a delta light: only this technique finds it
    else:
        scale = f * cos_x * g / p_sel
    if not _aim(i, out, p0, p1, p2, n0, n1, n2, w0, w1, w2, q0, q1, q2, eps_rel, surf.eps_abs):
        return False
    l0, l1, l2 = _light_value(lights, li, w0, w1, w2, u1, u2)
    _write_radiance(i, out, scale, weight, surf.reflectance, m, l0, l1, l2)
    return True


@nb.njit(inline="always", cache=True, error_model="numpy")
def _chosen_light_ray(i, p0, p1, p2, n0, n1, n2, o0, o1, o2, weight, m, surf, lights, cache,
                      infinite, st, ul, u1, u2, eps_rel, out):
    """A shadow ray to a point on a light chosen from the defensive mixture
    a p_tree + (1 - a) p_cell of the light tree at the hit point and the
    lights its cell learned from the photons (`light_cache`), or, in a
    fixed share of the choices, an infinite light by power (`infinite`
    None: the scene has none, and the loop is compiled without them).
    Writes row i of `out`, returns whether it may contribute."""
    tree = (lights[8], lights[9], lights[10], lights[11], lights[12], lights[13])
    row, share, total = read_cell(cache, p0, p1, p2, n0, n1, n2)
    st, um = next_float(st)
    if infinite is not None and um < infinite[1][0]:
        li = select_light(infinite[0], ul)
        p_tree = tree_pmf(tree, li, p0, p1, p2, n0, n1, n2)
    else:
        if infinite is not None:
            um = (um - infinite[1][0]) / (1.0 - infinite[1][0])
        if um < share:
            li, p_tree = sample_tree(tree, p0, p1, p2, n0, n1, n2, ul)
            if li < 0:
                return False
        else:
            li = pick_in_cell(cache, row, total, ul)
            p_tree = tree_pmf(tree, li, p0, p1, p2, n0, n1, n2)
    pmf = share * p_tree + (1.0 - share) * cell_pmf(cache, row, total, li)
    if infinite is not None:
        inf_cdf, q_inf = infinite[0], infinite[1][0]
        p_inf = inf_cdf[li] - (inf_cdf[li - 1] if li > 0 else 0.0)
        pmf = q_inf * p_inf + (1.0 - q_inf) * pmf
        if lights[0][li] == LIGHT_ENV:
            return _env_ray(i, p0, p1, p2, n0, n1, n2, o0, o1, o2, weight, m, surf, lights, infinite, li,
                            pmf, False, u1, u2, eps_rel, out)
    q0, q1, q2, w0, w1, w2, dist, g = _sample_light(lights, li, p0, p1, p2, u1, u2)
    if not (g > 0.0 and pmf > 0.0):
        return False
    cos_x = n0 * w0 + n1 * w1 + n2 * w2
    if not cos_x > 0.0:
        return False
    f = eval_bsdf(surf.kind[m], np.float64(surf.roughness[m]), n0, n1, n2, o0, o1, o2, w0, w1, w2)
    if not f > 0.0:
        return False
    if not _aim(i, out, p0, p1, p2, n0, n1, n2, w0, w1, w2, q0, q1, q2, eps_rel, surf.eps_abs):
        return False
    l0, l1, l2 = _light_value(lights, li, w0, w1, w2, u1, u2)
    _write_radiance(i, out, f * cos_x * g / pmf, weight, surf.reflectance, m, l0, l1, l2)
    return True


@nb.njit(inline="always", cache=True, error_model="numpy")
def _env_ray(i, p0, p1, p2, n0, n1, n2, o0, o1, o2, weight, m, surf, lights, infinite, li, p_sel, glossy,
             u1, u2, eps_rel, out):
    """A shadow ray toward a direction of the environment drawn by its
    luminance (light li, picked with probability p_sel), running past
    the scene's bounding sphere. On a glossy hit point the estimate is
    one-sample MIS against the BSDF technique, as for triangle lights."""
    env = _env_of(infinite)
    w0, w1, w2, p_dir = env_sample(env, u1, u2)
    if not (p_dir > 0.0 and p_sel > 0.0):
        return False
    cos_x = n0 * w0 + n1 * w1 + n2 * w2
    alpha = np.float64(surf.roughness[m])
    f = eval_bsdf(surf.kind[m], alpha, n0, n1, n2, o0, o1, o2, w0, w1, w2)
    if not f * cos_x > 0.0:
        return False
    if glossy:
        p_bsdf = glossy_pdf(alpha, n0, n1, n2, o0, o1, o2, w0, w1, w2)
        scale = f * cos_x / (C_LIGHT * p_sel * p_dir + (1.0 - C_LIGHT) * p_bsdf)
    else:
        scale = f * cos_x / (p_sel * p_dir)
    dist = _beyond_sphere(lights[2][li], lights[5][li, 0], p0, p1, p2)
    if not _aim(i, out, p0, p1, p2, n0, n1, n2, w0, w1, w2, p0 + dist * w0, p1 + dist * w1,
                p2 + dist * w2, eps_rel, surf.eps_abs):
        return False
    l0, l1, l2 = env_eval(env, w0, w1, w2)
    refl = surf.reflectance
    out[3][i, 0] = weight[i, 0] * refl[m, 0] * scale * l0
    out[3][i, 1] = weight[i, 1] * refl[m, 1] * scale * l1
    out[3][i, 2] = weight[i, 2] * refl[m, 2] * scale * l2
    return True


@nb.njit(inline="always", cache=True, error_model="numpy")
def _env_of(infinite):
    """The environment's arrays (`kernels.envmap.env_arrays`) in `infinite`."""
    return infinite[2], infinite[3], infinite[4], infinite[5], infinite[6]


@nb.njit(cache=True, error_model="numpy")
def choice_pmf(lights, cache, p0, p1, p2, n0, n1, n2, li):
    """(mixture, tree, cell) probabilities with which `_chosen_light_ray`
    at hit point p (normal n) picks light li, for tests and diagnostics."""
    tree = (lights[8], lights[9], lights[10], lights[11], lights[12], lights[13])
    row, share, total = read_cell(cache, p0, p1, p2, n0, n1, n2)
    p_tree = tree_pmf(tree, li, p0, p1, p2, n0, n1, n2)
    p_cell = cell_pmf(cache, row, total, li)
    return share * p_tree + (1.0 - share) * p_cell, p_tree, p_cell


@nb.njit(inline="always", cache=True, error_model="numpy")
def _bsdf_ray(i, p0, p1, p2, n0, n1, n2, o0, o1, o2, weight, m, surf, u1, u2, eps_rel, out):
    """A direction sampled from the glossy lobe, looking for an emitter;
    its radiance is W refl f cos, its pdf (1 - C_LIGHT) p_bsdf."""
    alpha = np.float64(surf.roughness[m])
    ok, w0, w1, w2, _scale, _spec = sample_bsdf(GLOSSY, True, 1.0, alpha, n0, n1, n2, o0, o1, o2,
                                                u1, u2, 0.5, True)
    if not ok:
        return False
    wl = math.sqrt(w0 * w0 + w1 * w1 + w2 * w2)
    w0, w1, w2 = w0 / wl, w1 / wl, w2 / wl
    f = eval_bsdf(GLOSSY, alpha, n0, n1, n2, o0, o1, o2, w0, w1, w2)
    p_bsdf = glossy_pdf(alpha, n0, n1, n2, o0, o1, o2, w0, w1, w2)
    cos_x = n0 * w0 + n1 * w1 + n2 * w2
    if not (f * cos_x > 0.0 and p_bsdf > 0.0):
        return False
    _write_ray(i, out, p0, p1, p2, n0, n1, n2, w0, w1, w2, FIRST_HIT, f * cos_x, weight,
               surf.reflectance, m, (1.0 - C_LIGHT) * p_bsdf, eps_rel, surf.eps_abs)
    return True


@nb.njit(cache=True, parallel=True, error_model="numpy")
def emitter_radiance(direction, radiance, pdf, prim, t, surf, total_power):
    """What BSDF-sampled rays (pdf > 0) bring from the triangles they hit
    first (`prim` into `surf`, distance `t`): radiance * Le / (C_LIGHT
    p_light + pdf) where the hit is the front of an emitter, else 0.
    p_light is the density with which light sampling picks that direction:
    the triangle's share of the power (pi A mean(Le) / total) over its
    solid angle (cos_y A / t^2)."""
    n = prim.shape[0]
    rgb = np.zeros((n, 3), np.float32)
    verts, tris, emit = surf.vertices, surf.triangles, surf.emission
    for i in nb.prange(n):
        tri = prim[i]
        if tri < 0 or not pdf[i] > 0.0:
            continue
        m = surf.tri_material[tri]
        le = (emit[m, 0] + emit[m, 1] + emit[m, 2]) / 3.0
        if not le > 0.0:
            continue
        a, b, c = verts[tris[tri, 0]], verts[tris[tri, 1]], verts[tris[tri, 2]]
        e10, e11, e12 = np.float64(b[0]) - a[0], np.float64(b[1]) - a[1], np.float64(b[2]) - a[2]
        e20, e21, e22 = np.float64(c[0]) - a[0], np.float64(c[1]) - a[1], np.float64(c[2]) - a[2]
        nx = e11 * e22 - e12 * e21
        ny = e12 * e20 - e10 * e22
        nz = e10 * e21 - e11 * e20
        nl = math.sqrt(nx * nx + ny * ny + nz * nz)
        cos_y = -(nx * direction[i, 0] + ny * direction[i, 1] + nz * direction[i, 2]) / nl
        if not cos_y > 0.0:       # one-sided: emits on its CCW front
            continue
        p_light = math.pi * le * np.float64(t[i]) ** 2 / (cos_y * total_power)
        k = 1.0 / (C_LIGHT * p_light + pdf[i])
        for j in range(3):
            rgb[i, j] = radiance[i, j] * emit[m, j] * k
    return rgb


# -- the coloured materials (kernels.materials) --------------------------------------
@nb.njit(inline="always", cache=True, error_model="numpy")
def _coloured_ray(i, p0, p1, p2, n0, n1, n2, o0, o1, o2, weight, m, surf, lights, infinite, total, mis,
                  ut, ul, u1, u2, eps_rel, out, frames):
    """Direct light at a hit point of a rough dielectric, a plastic or a
    conductor: the glossy hit point's one-sample MIS (a light chosen by
    power, or with probability 1 - C_LIGHT a direction from the hit point's
    BSDF), with an RGB BSDF. A rough dielectric's normal is its geometric
    one, so a light behind the surface is reached by transmission (|cos|)."""
    kind, row = surf.kind[m], surf.bsdf[m]
    if mis and ut >= C_LIGHT:
        return _coloured_bsdf_ray(i, p0, p1, p2, n0, n1, n2, o0, o1, o2, weight, kind, row, surf,
                                  ul, u1, u2, eps_rel, out, frames)
    power, cdf = lights[6], lights[7]
    li = select_light(cdf, ul)
    p_sel = power[li] / total
    c = C_LIGHT if mis else 1.0
    if infinite is not None and lights[0][li] == LIGHT_ENV:
        env = _env_of(infinite)
        w0, w1, w2, p_dir = env_sample(env, u1, u2)
        if not (p_dir > 0.0 and p_sel > 0.0):
            return False
        dist = _beyond_sphere(lights[2][li], lights[5][li, 0], p0, p1, p2)
        q0, q1, q2 = p0 + dist * w0, p1 + dist * w1, p2 + dist * w2
        p_light = p_sel * p_dir
        l0, l1, l2 = env_eval(env, w0, w1, w2)
    else:
        q0, q1, q2, w0, w1, w2, dist, g = _sample_light(lights, li, p0, p1, p2, u1, u2)
        if not g > 0.0:
            return False
        p_light = p_sel / g
        l0, l1, l2 = _light_value(lights, li, w0, w1, w2, u1, u2)
    pdf = c * p_light
    if mis and (lights[0][li] == LIGHT_TRIANGLE or lights[0][li] == LIGHT_ENV):
        pdf += (1.0 - C_LIGHT) * hp_pdf(kind, row, frames, i, n0, n1, n2, o0, o1, o2, w0, w1, w2)
    if not _aim(i, out, p0, p1, p2, n0, n1, n2, w0, w1, w2, q0, q1, q2, eps_rel, surf.eps_abs):
        return False
    out[3][i, 0] = weight[i, 0] * l0 / pdf
    out[3][i, 1] = weight[i, 1] * l1 / pdf
    out[3][i, 2] = weight[i, 2] * l2 / pdf
    return _tint_row(i, out, kind, row, n0, n1, n2, o0, o1, o2, w0, w1, w2, frames)


@nb.njit(inline="always", cache=True, error_model="numpy")
def _coloured_bsdf_ray(i, p0, p1, p2, n0, n1, n2, o0, o1, o2, weight, kind, row, surf, ul, u1, u2,
                       eps_rel, out, frames):
    """A direction from the hit point's BSDF, looking for an emitter (or the
    environment): radiance W f |cos|, pdf (1 - C_LIGHT) p_bsdf."""
    ok, w0, w1, w2, _t0, _t1, _t2 = hp_sample(kind, row, frames, i, n0, n1, n2, o0, o1, o2, ul, u1, u2)
    if not ok:
        return False
    wl = math.sqrt(w0 * w0 + w1 * w1 + w2 * w2)
    w0, w1, w2 = w0 / wl, w1 / wl, w2 / wl
    p_bsdf = hp_pdf(kind, row, frames, i, n0, n1, n2, o0, o1, o2, w0, w1, w2)
    if not p_bsdf > 0.0:
        return False
    origin, direction, tmax, radiance, pdfs = out
    origin[i, 0], origin[i, 1], origin[i, 2] = offset_origin(p0, p1, p2, n0, n1, n2, w0, w1, w2,
                                                             eps_rel, surf.eps_abs)
    direction[i, 0], direction[i, 1], direction[i, 2] = w0, w1, w2
    tmax[i] = FIRST_HIT
    pdfs[i] = (1.0 - C_LIGHT) * p_bsdf
    for k in range(3):
        radiance[i, k] = weight[i, k]
    return _tint_row(i, out, kind, row, n0, n1, n2, o0, o1, o2, w0, w1, w2, frames)


@nb.njit(inline="always", cache=True, error_model="numpy")
def _tint_row(i, out, kind, row, n0, n1, n2, o0, o1, o2, w0, w1, w2, frames):
    """Multiply row i's radiance by f(wo, wi) |cos| (rgb); whether it may contribute."""
    f0, f1, f2 = hp_eval(kind, row, frames, i, n0, n1, n2, o0, o1, o2, w0, w1, w2)
    c = abs(n0 * w0 + n1 * w1 + n2 * w2)
    out[3][i, 0] *= f0 * c
    out[3][i, 1] *= f1 * c
    out[3][i, 2] *= f2 * c
    return out[3][i, 0] + out[3][i, 1] + out[3][i, 2] > 0.0
