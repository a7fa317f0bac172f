"""Smooth meshes: the interpolated vertex normal as the shading normal, as
Mitsuba 3 shades meshes without face_normals (and its analytic spheres
and cylinders: `scene.mitsuba.shapes`).

At a hit on triangle tri (unit CCW geometric normal n) the shading normal
s is the vertex normals interpolated at the barycentrics and normalised,
turned to n's side. Eye paths and photons sample and evaluate every BSDF
kind around s (a smooth mirror reflects about s, glass refracts through
it) and hit points store s (facing the eye, as `paths.write_facing`
turns normals), so the gather and the direct-light rays use it; the
geometric normal still decides the side a ray arrives on and offsets the
spawned rays. Photons carry Veach's adjoint of the shading-normal BSDF
(Veach 1997, 5.3), as normal maps do (`kernels.shading`), here for
transmission too: a photon arriving from wi and leaving to wo is weighted
by f |wi.s| |wo.n| / (|wi.n| p(wo)) instead of f |wo.s| / p(wo), and a
deposit's flux by |wi.s| / |wi.n|.

Where a hit is not smooth: no normals in the scene (an empty array, so a
flat scene runs none of this), a flat mesh's zero normals, or a direction
that s and n put on opposite sides (a grazing ray at a silhouette: the
side, and glass's eta, would be ambiguous), the geometric normal is used;
Mitsuba would keep s there (a small grazing difference). A photon whose
sampled direction s and n put on opposite sides is absorbed (light that
would leak through the geometric surface). A material with a normal or
bump map keeps that map's normal, built on the face's frame."""
import math

import numba as nb


@nb.njit(inline="always", cache=True, error_model="numpy")
def smooth_normal(normals, tris, tri, u, v, n0, n1, n2, w0, w1, w2):
    """(smooth, shading normal s on n's side) at barycentrics (u, v) of
    triangle tri seen from direction w; (False, n) where not smooth."""
    if normals.shape[0] == 0:
        return False, n0, n1, n2
    t0, t1, t2 = tris[tri, 0], tris[tri, 1], tris[tri, 2]
    b = 1.0 - u - v
    s0 = b * normals[t0, 0] + u * normals[t1, 0] + v * normals[t2, 0]
    s1 = b * normals[t0, 1] + u * normals[t1, 1] + v * normals[t2, 1]
    s2 = b * normals[t0, 2] + u * normals[t1, 2] + v * normals[t2, 2]
    length = math.sqrt(s0 * s0 + s1 * s1 + s2 * s2)
    if not length > 0.0:
        return False, n0, n1, n2
    k = 1.0 / length if s0 * n0 + s1 * n1 + s2 * n2 >= 0.0 else -1.0 / length
    s0, s1, s2 = s0 * k, s1 * k, s2 * k
    if (s0 * w0 + s1 * w1 + s2 * w2) * (n0 * w0 + n1 * w1 + n2 * w2) <= 0.0:
        return False, n0, n1, n2
    return True, s0, s1, s2


@nb.njit(inline="always", cache=True, error_model="numpy")
def arrival_factor(n0, n1, n2, s0, s1, s2, w0, w1, w2):
    """|w.s| / |w.n| of a photon arriving from w (both nonzero and on one
    side, by `smooth_normal`): its deposit's flux factor."""
    return abs(s0 * w0 + s1 * w1 + s2 * w2) / abs(n0 * w0 + n1 * w1 + n2 * w2)


@nb.njit(inline="always", cache=True, error_model="numpy")
def smooth_adjoint(t0, t1, t2, k_in, n0, n1, n2, s0, s1, s2, d0, d1, d2):
    """A photon's throughput t = f |d.s| / p at a smooth hit made Veach's
    adjoint: times k_in |d.n| / |d.s|. Returns (ok, t); not ok where s
    and n put d on opposite sides."""
    cn = d0 * n0 + d1 * n1 + d2 * n2
    cs = d0 * s0 + d1 * s1 + d2 * s2
    if not cn * cs > 0.0:
        return False, 0.0, 0.0, 0.0
    k = k_in * abs(cn) / abs(cs)
    return True, t0 * k, t1 * k, t2 * k
