"""Triangle corners for the procedural building (`generate`): axis-aligned
rectangles, boxes tessellated into grids, and a torus knot in slices of its
tube. Pure functions of numbers; each returns float64 (m, 3, 3) corners,
counter-clockwise seen from the side a triangle faces."""
from __future__ import annotations

import numpy as np

from dosppm_core.scene import shapes

KNOT_TUBE = 0.3                             # shapes.torus_knot's default, in object units


def rects(axis: int, lo, hi, facing: int) -> np.ndarray:
    """Axis-aligned rectangles in the planes coord[axis] = lo[:, axis],
    spanning [lo, hi] in the other two axes, as two triangles each facing
    `facing` * axis. Corners run (lo, lo) (hi, lo) (hi, hi) (lo, hi) in
    the cyclic next two axes (a, b), and e_a x e_b = e_axis."""
    lo, hi = np.atleast_2d(lo).astype(np.float64), np.atleast_2d(hi).astype(np.float64)
    a, b = (axis + 1) % 3, (axis + 2) % 3
    quad = np.repeat(lo[:, None, :], 4, axis=1)
    quad[:, 1:3, a] = hi[:, None, a]
    quad[:, 2:4, b] = hi[:, None, b]
    if facing < 0:
        quad = quad[:, ::-1]
    return quad[:, [[0, 1, 2], [0, 2, 3]]].reshape(-1, 3, 3)


def flat(lo, hi, axis: int, value: float) -> tuple[np.ndarray, np.ndarray]:
    """The box [lo, hi] flattened to the plane coord[axis] = value."""
    lo, hi = np.array(lo, np.float64), np.array(hi, np.float64)
    lo[axis] = hi[axis] = value
    return lo, hi


def tessellated_box(lo, hi, grid: int) -> np.ndarray:
    """The box [lo, hi] facing out, each face a grid x grid mesh of quads
    (12 grid^2 triangles). Edges shared by two faces come from the same
    linspace, so the box is closed."""
    edges = [np.linspace(lo[k], hi[k], grid + 1) for k in range(3)]
    faces = []
    for axis in range(3):
        a, b = (axis + 1) % 3, (axis + 2) % 3
        ga, gb = np.meshgrid(np.arange(grid), np.arange(grid), indexing="ij")
        clo, chi = np.empty((grid * grid, 3)), np.empty((grid * grid, 3))
        clo[:, a], chi[:, a] = edges[a][ga.ravel()], edges[a][ga.ravel() + 1]
        clo[:, b], chi[:, b] = edges[b][gb.ravel()], edges[b][gb.ravel() + 1]
        for value, facing in ((lo[axis], -1), (hi[axis], +1)):
            clo[:, axis] = chi[:, axis] = value
            faces.append(rects(axis, clo, chi, facing))
    return np.concatenate(faces)


def object_rotation(yaw_deg: float) -> np.ndarray:
    """Turn about z by 90 degrees (a knot's lobe on top, its plane upright),
    then about the vertical by `yaw_deg`."""
    return shapes.rotation_matrix((0, 1, 0), yaw_deg) @ shapes.rotation_matrix((0, 0, 1), 90.0)


def knot_slices(tubular: int, radial: int, size: float, yaw_deg: float, centre_xz, rest_y: float,
                max_triangles: int):
    """A torus knot of `tubular` x `radial` quads, scaled by `size`, turned
    by `object_rotation(yaw_deg)`, centred over `centre_xz` with the lowest
    point of its tube at `rest_y`, in slices of its tube of at most
    `max_triangles`. The per-ring frame is placed in the world once; every
    vertex is then centre + r (cos k normal + sin k binormal), element-wise,
    so a ring shared by two slices has the same bits in both."""
    centre, normal, binormal = _knot_frame(tubular, size, yaw_deg, centre_xz, rest_y)
    angle = 2 * np.pi * np.arange(radial) / radial
    cos, sin = np.cos(angle)[None, :, None], np.sin(angle)[None, :, None]
    radius = KNOT_TUBE * size
    rows = max(1, max_triangles // (2 * radial))
    for i0 in range(0, tubular, rows):
        ring = np.arange(i0, min(i0 + rows, tubular) + 1) % tubular
        v = centre[ring][:, None] + radius * (cos * normal[ring][:, None] + sin * binormal[ring][:, None])
        a, b = v[:-1], np.roll(v[:-1], -1, axis=1)
        c, d = np.roll(v[1:], -1, axis=1), v[1:]
        # (i, k) (i, k+1) (i+1, k+1) (i+1, k): counter-clockwise from outside.
        yield np.stack([a, b, c, a, c, d], axis=2).reshape(-1, 3, 3)


def _knot_frame(tubular: int, size: float, yaw_deg: float, centre_xz, rest_y: float):
    """(centre, normal, binormal) of each ring of the knot, in the world."""
    t = 2 * np.pi * np.arange(tubular) / tubular
    centre, tangent = shapes.torus_knot_curve(t)
    # As shapes.torus_knot: a frame from the z axis, periodic along the knot.
    normal = tangent[:, 2:3] * -tangent + np.array([0.0, 0.0, 1.0])
    normal /= np.linalg.norm(normal, axis=1, keepdims=True)
    binormal = np.cross(tangent, normal)
    rot = object_rotation(yaw_deg)
    centre = (centre * size) @ rot.T
    lift = rest_y - (centre[:, 1].min() - KNOT_TUBE * size)
    centre += np.array([centre_xz[0], lift, centre_xz[1]])
    return centre, normal @ rot.T, binormal @ rot.T
