"""The chunk tree: the kd-tree whose leaves are the chunks (§4.1).

Every chunk is a box; the boxes tile the root box (the scene's bounds grown
by a small margin) without overlap. The tree answers one question exactly,
for any point and direction: which chunk does a ray at this point, heading
this way, travel through next? That answer defines the neighbour behind
every point of every portal, T-junctions, edges and corners included.

The rule for a point lying exactly on a split plane: it belongs to the side
the direction points into; a direction parallel to the plane (component
exactly 0) goes to the upper side. Every caller uses `locate`, so the rule is
applied the same way everywhere.
"""
from __future__ import annotations

from dataclasses import dataclass

import numba
import numpy as np

from dosppm_core import arrays

LEAF = -1
OUTSIDE = -1


@dataclass
class ChunkTree:
    """Flat kd-tree arrays (msgpack- and numba-friendly). Node 0 is the root.

    Inner node i splits along `axis[i]` at `split[i]`; `child[i]` holds its
    lower and upper child nodes. A leaf has axis -1 and `child[i] = (chunk,
    -1)`. `boxes[k]` is chunk k's box as (lo, hi) rows."""
    axis: np.ndarray    # int8 (nodes,)
    split: np.ndarray   # float64 (nodes,)
    child: np.ndarray   # int32 (nodes, 2)
    boxes: np.ndarray   # float64 (chunks, 2, 3)

    @classmethod
    def single(cls, box) -> "ChunkTree":
        """One chunk covering `box` (the unchunked case)."""
        box = np.asarray(box, np.float64).reshape(1, 2, 3)
        return cls(np.array([LEAF], np.int8), np.zeros(1), np.array([[0, -1]], np.int32), box)

    @property
    def chunk_count(self) -> int:
        return int(self.boxes.shape[0])

    @property
    def root_box(self) -> np.ndarray:
        return np.stack([self.boxes[:, 0].min(axis=0), self.boxes[:, 1].max(axis=0)])

    def locate(self, points: np.ndarray, directions: np.ndarray) -> np.ndarray:
        """Chunk of each (point, direction); -1 outside the root box."""
        return _locate(self.axis, self.split, self.child, self.root_box,
                       np.ascontiguousarray(points, np.float64),
                       np.ascontiguousarray(directions, np.float64))

    def validate(self) -> None:
        """Raise ValueError unless the leaves' boxes are exactly the boxes
        the splits carve out of the root box (a corrupt store fails here)."""
        n = self.axis.shape[0]
        if not (self.split.shape == (n,) and self.child.shape == (n, 2)
                and self.boxes.ndim == 3 and self.boxes.shape[1:] == (2, 3)):
            raise ValueError("chunk tree arrays have inconsistent shapes")
        seen = np.zeros(self.chunk_count, np.int64)
        stack = [(0, self.root_box.copy(), 0)]
        while stack:
            node, box, depth = stack.pop()
            if not 0 <= node < n or depth > 64:
                raise ValueError(f"chunk tree node {node} out of range or cycle")
            a = int(self.axis[node])
            if a == LEAF:
                k = int(self.child[node, 0])
                if not 0 <= k < self.chunk_count or not np.array_equal(self.boxes[k], box):
                    raise ValueError(f"chunk tree leaf {node}: box of chunk {k} does not match")
                seen[k] += 1
                continue
            s = float(self.split[node])
            if not (0 <= a < 3 and box[0, a] < s < box[1, a]):
                raise ValueError(f"chunk tree node {node}: split {s} outside its box")
            lower, upper = box.copy(), box.copy()
            lower[1, a] = s
            upper[0, a] = s
            stack.append((int(self.child[node, 0]), lower, depth + 1))
            stack.append((int(self.child[node, 1]), upper, depth + 1))
        if not np.all(seen == 1):
            raise ValueError("chunk tree: every chunk must be exactly one leaf")

    def to_wire(self) -> dict:
        """msgpack-ready: raw little-endian bytes plus shapes."""
        return {"axis": arrays.raw(self.axis, "|i1"), "split": arrays.raw(self.split, "<f8"),
                "child": arrays.raw(self.child, "<i4"), "boxes": arrays.raw(self.boxes, "<f8"),
                "nodes": int(self.axis.shape[0]), "chunks": self.chunk_count}

    @classmethod
    def from_wire(cls, d: dict) -> "ChunkTree":
        n, c = int(d["nodes"]), int(d["chunks"])
        fields = (("axis", "|i1", (n,)), ("split", "<f8", (n,)), ("child", "<i4", (n, 2)),
                  ("boxes", "<f8", (c, 2, 3)))
        tree = cls(*(arrays.from_bytes(d[name], dtype, shape, f"chunk tree {name!r}", copy=True)
                     for name, dtype, shape in fields))
        tree.validate()
        return tree


@numba.njit(cache=True)
def _locate_one(axis, split, child, root, p, d):
    """`p`, `d`: 3-tuples (no allocation per ray)."""
    for a in range(3):
        if p[a] < root[0, a] or p[a] > root[1, a]:
            return OUTSIDE
        if p[a] == root[0, a] and d[a] < 0:
            return OUTSIDE
        if p[a] == root[1, a] and d[a] > 0:
            return OUTSIDE
    node = 0
    while axis[node] != LEAF:
        a = axis[node]
        s = split[node]
        if p[a] > s or (p[a] == s and d[a] >= 0.0):
            node = child[node, 1]
        else:
            node = child[node, 0]
    return child[node, 0]


@numba.njit(cache=True, parallel=True)
def _locate(axis, split, child, root, points, directions):
    out = np.empty(points.shape[0], np.int32)
    for i in numba.prange(points.shape[0]):
        p = (points[i, 0], points[i, 1], points[i, 2])
        d = (directions[i, 0], directions[i, 1], directions[i, 2])
        out[i] = _locate_one(axis, split, child, root, p, d)
    return out
