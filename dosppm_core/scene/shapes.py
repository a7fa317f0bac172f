"""Procedural triangle meshes.

Every generator returns `(vertices, faces)`: float64 (n, 3) positions and
int64 (m, 3) vertex indices. Winding is counter-clockwise seen from the
front, so the geometric normal (v1 - v0) x (v2 - v0) points out of closed
shapes and along +z for the rectangle; an emissive material emits on that
side (see `scene.py`). Closed shapes share their vertices, so they are
watertight: every edge belongs to exactly two triangles, which refraction
needs to know when a ray is inside.

| shape        | object space                    | triangles               |
|--------------|---------------------------------|-------------------------|
| `rectangle`  | [-1, 1]^2 at z = 0, normal +z   | 2                       |
| `box`        | [-1, 1]^3                       | 12                      |
| `ico_sphere` | unit sphere                     | 20 * 4**subdivisions    |
| `uv_sphere`  | unit sphere, poles on +-z       | 2 * segments * (rings-1)|
| `torus_knot` | about [-1.5, 1.8] x [-1.8, 1.8] x [-0.8, 0.8] | 2 * tubular * radial |

The conventions are Mitsuba's (`rectangle`, `cube`, `sphere` plugins), so a
transform written for Mitsuba places the same surface here.
"""
from __future__ import annotations

import math

import numpy as np


def rectangle() -> tuple[np.ndarray, np.ndarray]:
    """The square [-1, 1]^2 in the xy-plane, facing +z."""
    vertices = np.array([[-1, -1, 0], [1, -1, 0], [1, 1, 0], [-1, 1, 0]], np.float64)
    faces = np.array([[0, 1, 2], [0, 2, 3]], np.int64)
    return vertices, faces


def box() -> tuple[np.ndarray, np.ndarray]:
    """The cube [-1, 1]^3 with outward faces; corner i has coordinate
    bits (x, y, z) = (i & 1, i & 2, i & 4) mapped to -1 / +1."""
    i = np.arange(8)
    vertices = np.stack([i & 1, (i >> 1) & 1, (i >> 2) & 1], axis=1) * 2.0 - 1.0
    # One quad per side, listed counter-clockwise as seen from outside.
    quads = np.array([
        [0, 4, 6, 2],  # -x
        [1, 3, 7, 5],  # +x
        [0, 1, 5, 4],  # -y
        [2, 6, 7, 3],  # +y
        [0, 2, 3, 1],  # -z
        [4, 5, 7, 6],  # +z
    ], np.int64)
    return vertices, quads_to_triangles(quads)


def quads_to_triangles(quads: np.ndarray) -> np.ndarray:
    """Split each quad (a, b, c, d) into (a, b, c) and (a, c, d), the fan
    that OBJ readers such as trimesh and Mitsuba use, keeping the winding."""
    quads = np.asarray(quads, np.int64).reshape(-1, 4)
    tris = np.stack([quads[:, [0, 1, 2]], quads[:, [0, 2, 3]]], axis=1)
    return tris.reshape(-1, 3)


# -- spheres ---------------------------------------------------------------

def _icosahedron() -> tuple[np.ndarray, np.ndarray]:
    phi = (1.0 + math.sqrt(5.0)) / 2.0
    vertices = np.array([
        [-1, phi, 0], [1, phi, 0], [-1, -phi, 0], [1, -phi, 0],
        [0, -1, phi], [0, 1, phi], [0, -1, -phi], [0, 1, -phi],
        [phi, 0, -1], [phi, 0, 1], [-phi, 0, -1], [-phi, 0, 1],
    ], np.float64)
    faces = np.array([
        [0, 11, 5], [0, 5, 1], [0, 1, 7], [0, 7, 10], [0, 10, 11],
        [1, 5, 9], [5, 11, 4], [11, 10, 2], [10, 7, 6], [7, 1, 8],
        [3, 9, 4], [3, 4, 2], [3, 2, 6], [3, 6, 8], [3, 8, 9],
        [4, 9, 5], [2, 4, 11], [6, 2, 10], [8, 6, 7], [9, 8, 1],
    ], np.int64)
    return _normalize(vertices), faces


def _subdivide(vertices: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Split every triangle into four through its edge midpoints, pushed out
    to the unit sphere. Each edge's midpoint is created once (keyed by its
    sorted end points), so the result stays watertight."""
    n = len(vertices)
    edges = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    lo, hi = edges.min(axis=1), edges.max(axis=1)
    keys, first, inverse = np.unique(lo * n + hi, return_index=True, return_inverse=True)
    mids = _normalize(vertices[lo[first]] + vertices[hi[first]])
    ab, bc, ca = inverse.reshape(3, -1) + n
    a, b, c = faces.T
    new_faces = np.concatenate([
        np.stack([a, ab, ca], 1), np.stack([b, bc, ab], 1),
        np.stack([c, ca, bc], 1), np.stack([ab, bc, ca], 1)])
    return np.concatenate([vertices, mids]), new_faces


def ico_sphere(subdivisions: int = 3) -> tuple[np.ndarray, np.ndarray]:
    """Unit geodesic sphere: an icosahedron split `subdivisions` times
    (20 * 4**subdivisions nearly equal triangles, no poles)."""
    if not 0 <= int(subdivisions) <= 8:
        raise ValueError(f"ico_sphere: subdivisions must lie in 0..8, got {subdivisions}")
    vertices, faces = _icosahedron()
    for _ in range(int(subdivisions)):
        vertices, faces = _subdivide(vertices, faces)
    return vertices, faces


def uv_sphere(rings: int = 32, segments: int = 64) -> tuple[np.ndarray, np.ndarray]:
    """Unit latitude-longitude sphere with poles on +-z: `rings` bands of
    latitude, `segments` of longitude; the pole caps are triangle fans (no
    degenerate triangles) and the seam shares its vertices."""
    if rings < 2 or segments < 3:
        raise ValueError(f"uv_sphere: need rings >= 2 and segments >= 3, got {rings}, {segments}")
    theta = np.pi * np.arange(1, rings) / rings
    phi = 2 * np.pi * np.arange(segments) / segments
    st, ct = np.sin(theta)[:, None], np.cos(theta)[:, None]
    ring_pts = np.stack([st * np.cos(phi), st * np.sin(phi), np.repeat(ct, segments, axis=1)], -1)
    vertices = np.concatenate([[[0.0, 0.0, 1.0]], ring_pts.reshape(-1, 3), [[0.0, 0.0, -1.0]]])
    south = len(vertices) - 1
    j = np.arange(segments)
    jn = (j + 1) % segments
    ring = lambda r, col: 1 + r * segments + col  # noqa: E731 - index of ring r, column col
    north_cap = np.stack([np.zeros_like(j), ring(0, j), ring(0, jn)], 1)
    south_cap = np.stack([np.full_like(j, south), ring(rings - 2, jn), ring(rings - 2, j)], 1)
    r = np.arange(rings - 2)[:, None]
    quads = np.stack([ring(r, j), ring(r + 1, j), ring(r + 1, jn), ring(r, jn)], -1)
    faces = np.concatenate([north_cap, quads_to_triangles(quads.reshape(-1, 4)), south_cap])
    return vertices, faces.astype(np.int64)


def _normalize(v: np.ndarray) -> np.ndarray:
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


# -- the high-polygon glass object ----------------------------------------

def torus_knot_curve(t: np.ndarray, p: int = 2, q: int = 3) -> tuple[np.ndarray, np.ndarray]:
    """Centre line of the (p, q) torus knot on the torus of radii 1 and 0.5
    (z is the torus axis), and its unit tangent, at parameters `t` in
    [0, 2 pi)."""
    r = 1.0 + 0.5 * np.cos(q * t)
    dr = -0.5 * q * np.sin(q * t)
    cp, sp = np.cos(p * t), np.sin(p * t)
    centre = np.stack([r * cp, r * sp, 0.5 * np.sin(q * t)], axis=1)
    tangent = np.stack([dr * cp - r * p * sp, dr * sp + r * p * cp, 0.5 * q * np.cos(q * t)], axis=1)
    return centre, _normalize(tangent)


def torus_knot(p: int = 2, q: int = 3, tube_radius: float = 0.3,
               tubular_segments: int = 768, radial_segments: int = 72) -> tuple[np.ndarray, np.ndarray]:
    """A closed tube of `tube_radius` around the (p, q) torus knot: a
    periodic grid of `tubular_segments` x `radial_segments` quads, hence
    watertight (genus 1) with 2 * tubular * radial triangles.

    The defaults give 110,592 triangles of nearly square aspect (the centre
    line is 15.9 long, the tube 1.88 round). For (2, 3) the tube does not
    touch itself while `tube_radius` < 0.41: distinct strands pass 0.83
    apart at least, and the centre line bends no tighter than radius 0.71.
    The cross-section frame is built from the z axis, not Frenet's, so it is
    periodic and the tube closes without a twist at the seam.
    """
    t = 2 * np.pi * np.arange(tubular_segments) / tubular_segments
    centre, tangent = torus_knot_curve(t, p, q)
    # The tangent is never parallel to z (the knot always winds around the
    # axis), so this normal is well defined everywhere.
    z = np.array([0.0, 0.0, 1.0])
    normal = _normalize(z - tangent[:, 2:3] * tangent)
    binormal = np.cross(tangent, normal)
    angle = 2 * np.pi * np.arange(radial_segments) / radial_segments
    ring = np.cos(angle)[None, :, None] * normal[:, None] + np.sin(angle)[None, :, None] * binormal[:, None]
    vertices = (centre[:, None] + tube_radius * ring).reshape(-1, 3)
    i = np.arange(tubular_segments)[:, None]
    k = np.arange(radial_segments)[None, :]
    idx = lambda a, b: (a % tubular_segments) * radial_segments + b % radial_segments  # noqa: E731
    # (i, k) -> (i, k+1) -> (i+1, k+1) turns counter-clockwise seen from
    # outside: d(angle) x d(t) is the outward radial direction.
    quads = np.stack([idx(i, k), idx(i, k + 1), idx(i + 1, k + 1), idx(i + 1, k)], -1)
    return vertices, quads_to_triangles(quads.reshape(-1, 4))


def rotation_matrix(axis, degrees: float) -> np.ndarray:
    """3x3 right-handed rotation by `degrees` about `axis`: counter-clockwise
    looking down the axis towards the origin, as Mitsuba's `rotate`."""
    k = np.asarray(axis, np.float64) / np.linalg.norm(axis)
    cross = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    sin, cos = _sin_cos_degrees(degrees)
    return np.eye(3) + sin * cross + (1 - cos) * cross @ cross


def _sin_cos_degrees(degrees: float) -> tuple[float, float]:
    """Exact for multiples of 90 degrees, so a wall turned by 90 degrees
    lands exactly on its plane instead of 1e-14 off it."""
    if degrees % 90 == 0:
        quarter = int(degrees // 90) % 4
        return (0.0, 1.0, 0.0, -1.0)[quarter], (1.0, 0.0, -1.0, 0.0)[quarter]
    a = math.radians(degrees)
    return math.sin(a), math.cos(a)


def glass_knot() -> tuple[np.ndarray, np.ndarray]:
    """The high-polygon (110,592 triangles) closed glass object of the
    built-in `cornell-glass` scene: the default `torus_knot`. Deterministic;
    built in about 20 ms."""
    return torus_knot()
