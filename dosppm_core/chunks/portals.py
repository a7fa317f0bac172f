"""Exact portal traversal: a ray searched chunk by chunk finds the same
first hit as in the unchunked scene.

A ray keeps its origin and direction for its whole flight; in chunk k it
searches only its parametric interval [t_enter, t_exit] inside k's box
(widened by `eps` on both ends, and chunks hold every triangle within
`INSERT_MARGIN` of their box, so a hit on a portal is never lost between two
chunks). Embree's tnear is fixed at 0, so the search starts from the origin
moved to t_enter - eps; Embree's tmax ends it at t_exit + eps. A ray that
finds nothing continues in the chunk behind the face it leaves through,
located by `ChunkTree.locate` at the exit point snapped onto that face.

The cases, each tested:
- exit through an edge or corner: every axis whose plane is reached at
  t_exit is snapped, so `locate` picks the diagonal neighbour directly;
- a ray lying in a portal plane (direction component 0): the tie rule sends
  it to the upper side, consistently, and it never crosses the plane;
- a ray starting on a portal: located by the direction it heads in;
- a hit on a triangle duplicated across a portal: the first chunk whose
  interval contains it finds it; the ray stops there, so never twice;
- leaving the root box: next chunk -1 (escaped).
"""
from __future__ import annotations

import numba
import numpy as np

from dosppm_core.chunks.tree import OUTSIDE, ChunkTree, _locate_one

PORTAL_EPS = 1e-6    # interval widening, relative to the scene diagonal
INSERT_MARGIN = 4e-6  # chunks hold triangles this close to their box (x diagonal)


def enter(tree: ChunkTree, origin: np.ndarray, direction: np.ndarray):
    """(chunk, tmin) where each ray starts: the chunk holding its origin, or
    for an origin outside the root box (a camera outside the scene) the
    chunk where it enters, with tmin the entry distance; chunk -1 if it
    misses the scene."""
    return _enter(tree.axis, tree.split, tree.child, tree.root_box,
                  np.ascontiguousarray(origin, np.float32), np.ascontiguousarray(direction, np.float32))


def exit_chunk(tree: ChunkTree, chunk: int, origin: np.ndarray, direction: np.ndarray):
    """(t_exit float64, next chunk int32, -1 = leaves the scene) of rays in `chunk`."""
    return _exit(tree.axis, tree.split, tree.child, tree.root_box, tree.boxes[chunk], chunk,
                 np.ascontiguousarray(origin, np.float32), np.ascontiguousarray(direction, np.float32))


def intersect_in_chunk(accel, tree: ChunkTree, chunk: int, origin, direction, tmin, eps: float,
                       tmax=None):
    """Closest hits of rays within their interval in `chunk`, ending at
    `tmax` where given (shadow rays: the light).

    Returns (prim, t, u, v, next chunk, t_exit): `prim` -1 where the ray found
    nothing in this chunk, in which case it continues in `next` (or escapes
    when `next` is -1) with tmin = t_exit."""
    t_exit, nxt = exit_chunk(tree, chunk, origin, direction)
    limit = t_exit + eps
    if tmax is not None:
        limit = np.minimum(limit, tmax)
    prim, t, u, v = accel.intersect(origin, direction, limit.astype(np.float32))
    # From its own origin a ray gives bit-identical hits to the unchunked
    # trace. Only a hit before tmin (a triangle this chunk shares with one
    # already searched, hit outside this box) needs the search restarted
    # at tmin - eps; moving the origin costs float32 rounding, so it is
    # done for those rays alone.
    early = np.flatnonzero((prim >= 0) & (t < tmin - eps))
    if len(early):
        shift = tmin[early].astype(np.float64) - eps
        d = direction[early]
        o = (origin[early] + shift[:, None] * d).astype(np.float32)
        p2, t2, u2, v2 = accel.intersect(o, d, np.maximum(limit[early] - shift, 0.0))
        prim[early], t[early], u[early], v[early] = p2, t2 + shift, u2, v2
    return prim, t, u, v, nxt, t_exit


@numba.njit(cache=True)
def _axis_slab(lo, hi, o, d):
    """(entry, exit) of one axis's slab; (-inf, inf) when parallel and
    inside it, (inf, -inf) when parallel and outside."""
    if d != 0.0:
        ta, tb = (lo - o) / d, (hi - o) / d
        return (ta, tb) if ta <= tb else (tb, ta)
    if o < lo or o > hi:
        return np.inf, -np.inf
    return -np.inf, np.inf


@numba.njit(cache=True)
def _slab(lo, hi, o, d):
    """(entry, exit, per-axis exit distances) of the ray through the box.
    Scalars and tuples only: this runs once per ray per chunk and must not
    allocate."""
    ax, bx = _axis_slab(lo[0], hi[0], o[0], d[0])
    ay, by = _axis_slab(lo[1], hi[1], o[1], d[1])
    az, bz = _axis_slab(lo[2], hi[2], o[2], d[2])
    return max(ax, ay, az), min(bx, by, bz), (bx, by, bz)


@numba.njit(cache=True)
def _clamped(o, d, t, box):
    return (min(max(o[0] + t * d[0], box[0, 0]), box[1, 0]),
            min(max(o[1] + t * d[1], box[0, 1]), box[1, 1]),
            min(max(o[2] + t * d[2], box[0, 2]), box[1, 2]))


@numba.njit(cache=True, parallel=True)
def _enter(axis, split, child, root, origin, direction):
    n = origin.shape[0]
    chunk = np.empty(n, np.int32)
    tmin = np.zeros(n, np.float32)
    for i in numba.prange(n):
        p = (np.float64(origin[i, 0]), np.float64(origin[i, 1]), np.float64(origin[i, 2]))
        d = (np.float64(direction[i, 0]), np.float64(direction[i, 1]), np.float64(direction[i, 2]))
        inside = True
        for a in range(3):
            if p[a] < root[0, a] or p[a] > root[1, a]:
                inside = False
        if inside:
            chunk[i] = _locate_one(axis, split, child, root, p, d)
            continue
        t0, t1, _te = _slab(root[0], root[1], p, d)
        if not (t0 <= t1 and t1 > 0.0):
            chunk[i] = OUTSIDE
            continue
        chunk[i] = _locate_one(axis, split, child, root, _clamped(p, d, t0, root), d)
        tmin[i] = t0    # its float32 rounding is far inside the search's eps widening
    return chunk, tmin


@numba.njit(cache=True, parallel=True)
def _exit(axis, split, child, root, box, chunk, origin, direction):
    n = origin.shape[0]
    t_exit = np.empty(n)
    nxt = np.empty(n, np.int32)
    for i in numba.prange(n):
        p = (np.float64(origin[i, 0]), np.float64(origin[i, 1]), np.float64(origin[i, 2]))
        d = (np.float64(direction[i, 0]), np.float64(direction[i, 1]), np.float64(direction[i, 2]))
        _t0, t1, te = _slab(box[0], box[1], p, d)
        t_exit[i] = t1
        q = _clamped(p, d, t1, box)
        # Snap exactly onto the faces left through (one, or two or three at
        # an edge or corner), so `locate` sends the point across them.
        q = (_snap(q[0], te[0], t1, d[0], box, 0), _snap(q[1], te[1], t1, d[1], box, 1),
             _snap(q[2], te[2], t1, d[2], box, 2))
        k = _locate_one(axis, split, child, root, q, d)
        # k == chunk is impossible unless the ray started behind the box;
        # treat that as leaving (never loop).
        nxt[i] = OUTSIDE if k == chunk else k
    return t_exit, nxt


@numba.njit(cache=True)
def _snap(q, te, t1, d, box, a):
    if te == t1:
        return box[1, a] if d > 0 else box[0, a]
    return q
