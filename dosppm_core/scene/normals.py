"""Vertex normals of smooth meshes: the shading normals Mitsuba 3
interpolates across a mesh's triangles unless it sets face_normals.

A mesh file's own normals move with the inverse transpose of its
to_world; a mesh without computes Mitsuba's (src/render/mesh.cpp,
`recompute_vertex_normals`, v3.9): at each vertex the sum of the unit
normals of the triangles around it weighted by their angles there
(Thuermer and Wuethrich 1998), from the transformed positions, (1, 0, 0)
where that sum vanishes. The kernels normalise after interpolating and
turn the result to the winding's side (`kernels.smooth`)."""
from __future__ import annotations

import numpy as np

from dosppm_core.scene.errors import SceneError

COMPUTED = "computed"     # `SceneBuilder.add_mesh(normals=...)`: Mitsuba's own


def smooth_normals(normals, local, world: np.ndarray, faces: np.ndarray, transform, where: str):
    """A mesh's world-space vertex normals (float64 (nv, 3)) or None for a
    flat one. `normals`: None, COMPUTED, or (nv, 3) in the frame of the
    `local` vertices, which `transform` (4x4 or None) took to `world`."""
    if normals is None:
        return None
    if isinstance(normals, str):
        if normals != COMPUTED:
            raise SceneError(f"{where}: unknown normals {normals!r}")
        return angle_weighted_normals(world, faces)
    n = np.asarray(normals, np.float64)
    if n.shape != (len(world), 3) or not np.all(np.isfinite(n)):
        raise SceneError(f"{where}: vertex normals must be {len(world)} finite (x, y, z) triples")
    if transform is not None:
        n = n @ np.linalg.inv(np.asarray(transform, np.float64)[:3, :3])    # n M^-1 = (M^-T n^T)^T
    length = np.linalg.norm(n, axis=1, keepdims=True)
    return np.divide(n, length, out=np.zeros_like(n), where=length > 0)


def angle_weighted_normals(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Mitsuba's computed vertex normals of a triangle mesh (unit, float64)."""
    v = np.asarray(vertices, np.float64)
    corners = v[faces]                                              # (T, 3, 3)
    n = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
    area = np.linalg.norm(n, axis=1)
    ok = area > 0
    n = n[ok] / area[ok, None]
    out = np.zeros_like(v)
    for j in range(3):
        d0 = _unit(corners[ok, (j + 1) % 3] - corners[ok, j])
        d1 = _unit(corners[ok, (j + 2) % 3] - corners[ok, j])
        angle = np.arccos(np.clip(np.einsum("ij,ij->i", d0, d1), -1.0, 1.0))
        np.add.at(out, faces[ok, j], n * angle[:, None])
    length = np.linalg.norm(out, axis=1)
    out[length == 0] = (1.0, 0.0, 0.0)          # Mitsuba's "bogus value"
    length[length == 0] = 1.0
    return out / length[:, None]


def _unit(x: np.ndarray) -> np.ndarray:
    length = np.linalg.norm(x, axis=1, keepdims=True)
    return np.divide(x, length, out=np.zeros_like(x), where=length > 0)
