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

from .chunktree import OUTSIDE, ChunkTree, _locate_one

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


def intersect_in_chunk(accel, tree: ChunkTree, chunk: int, origin, direction, tmin, eps: float):
    """Closest hits of rays within their interval in `chunk`.

    Returns (prim, t, u, v, next chunk, t_exit): `prim` -1 where the ray found
    nothing in this chunk, in which case it continues in `next` (or escapes
    when `next` is -1) with tmin = t_exit."""
    t_exit, nxt = exit_chunk(tree, chunk, origin, direction)
    tmax = (t_exit + eps).astype(np.float32)
    prim, t, u, v = accel.intersect(origin, direction, tmax)
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
        p2, t2, u2, v2 = accel.intersect(o, d, np.maximum(t_exit[early] + eps - shift, 0.0))
        prim[early], t[early], u[early], v[early] = p2, t2 + shift, u2, v2
    return prim, t, u, v, nxt, t_exit


@numba.njit(cache=True)
def _slab(lo, hi, o, d):
    """Entry and exit distance of the ray through the box, and per axis the
    exit distance (inf for an axis the ray runs parallel to)."""
    t0, t1 = -np.inf, np.inf
    texit = np.full(3, np.inf)
    for a in range(3):
        if d[a] != 0.0:
            inv = 1.0 / d[a]
            ta, tb = (lo[a] - o[a]) * inv, (hi[a] - o[a]) * inv
            if ta > tb:
                ta, tb = tb, ta
            t0, t1 = max(t0, ta), min(t1, tb)
            texit[a] = tb
        elif o[a] < lo[a] or o[a] > hi[a]:
            return np.inf, -np.inf, texit
    return t0, t1, texit


@numba.njit(cache=True)
def _enter(axis, split, child, root, origin, direction):
    n = origin.shape[0]
    chunk = np.empty(n, np.int32)
    tmin = np.zeros(n, np.float32)
    p = np.empty(3)
    d = np.empty(3)
    for i in range(n):
        for a in range(3):
            p[a], d[a] = origin[i, a], direction[i, a]
        inside = True
        for a in range(3):
            if p[a] < root[0, a] or p[a] > root[1, a]:
                inside = False
        if inside:
            chunk[i] = _locate_one(axis, split, child, root, p, d)
            continue
        t0, t1, _ = _slab(root[0], root[1], p, d)
        if not (t0 <= t1 and t1 > 0.0):
            chunk[i] = OUTSIDE
            continue
        q = np.empty(3)
        for a in range(3):
            q[a] = min(max(p[a] + t0 * d[a], root[0, a]), root[1, a])
        chunk[i] = _locate_one(axis, split, child, root, q, d)
        tmin[i] = t0    # its float32 rounding is far inside the search's eps widening
    return chunk, tmin


@numba.njit(cache=True)
def _exit(axis, split, child, root, box, chunk, origin, direction):
    n = origin.shape[0]
    t_exit = np.empty(n)
    nxt = np.empty(n, np.int32)
    p = np.empty(3)
    d = np.empty(3)
    q = np.empty(3)
    for i in range(n):
        for a in range(3):
            p[a], d[a] = origin[i, a], direction[i, a]
        _t0, t1, texit = _slab(box[0], box[1], p, d)
        t_exit[i] = t1
        for a in range(3):
            if texit[a] == t1:      # the faces left through: snap exactly onto them
                q[a] = box[1, a] if d[a] > 0 else box[0, a]
            else:
                q[a] = min(max(p[a] + t1 * d[a], box[0, a]), box[1, a])
        k = _locate_one(axis, split, child, root, q, d)
        # The snapped point lies on this box's exit faces and `locate`
        # sends it across them, so k == chunk is impossible unless the ray
        # started behind the box; treat that as leaving (never loop).
        nxt[i] = OUTSIDE if k == chunk else k
    return t_exit, nxt
