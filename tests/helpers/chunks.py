"""Test helpers: chunk a scene in memory without the subdivider, so the
traversal is tested independently of it. Insertion here is by bounding-box
overlap, a superset of the exact test; extra triangles cannot change a first
hit, because a chunk only accepts hits inside its own interval."""
from __future__ import annotations

import numpy as np

from dosppm_core.chunks.portals import INSERT_MARGIN
from dosppm_core.chunks.store import ChunkGeometry
from dosppm_core.chunks.tree import LEAF, ChunkTree


def uniform_tree(box, cells) -> ChunkTree:
    """A kd-tree cutting `box` into cells[0] x cells[1] x cells[2] equal boxes."""
    box = np.asarray(box, np.float64)
    return lattice_tree(box, [box[0, a] + (box[1, a] - box[0, a]) * np.arange(1, cells[a]) / cells[a]
                              for a in range(3)])


def lattice_tree(box, planes) -> ChunkTree:
    """A kd-tree cutting `box` at the given split planes per axis (lists of
    interior coordinates): a lattice of len+1 boxes per axis."""
    box = np.asarray(box, np.float64)
    axis, split, child, boxes = [], [], [], []

    def build(lo, hi, cuts):
        node = len(axis)
        axis.append(LEAF)
        split.append(0.0)
        child.append([len(boxes), -1])
        a = next((a for a in range(3) if len(cuts[a])), None)
        if a is None:
            boxes.append(np.stack([lo, hi]))
            return node
        k = len(cuts[a]) // 2
        s = float(cuts[a][k])
        lower_hi, upper_lo = hi.copy(), lo.copy()
        lower_hi[a] = upper_lo[a] = s
        lower, upper = list(cuts), list(cuts)
        lower[a], upper[a] = cuts[a][:k], cuts[a][k + 1:]
        axis[node], split[node] = a, s
        left = build(lo, lower_hi, lower)
        right = build(upper_lo, hi, upper)
        child[node] = [left, right]
        return node

    build(box[0].copy(), box[1].copy(), [list(p) for p in planes])
    return ChunkTree(np.array(axis, np.int8), np.array(split), np.array(child, np.int32), np.array(boxes))


def skewed_tree(box, rng, leaves: int) -> ChunkTree:
    """Random kd-tree with `leaves` leaves: splits at random fractions on
    random axes, so faces meet in T-junctions."""
    box = np.asarray(box, np.float64)
    tree = ChunkTree.single(box)
    axis, split, child = list(tree.axis), list(tree.split), [list(c) for c in tree.child]
    boxes = [box.copy()]
    leaf_node = {0: 0}   # chunk -> node
    while len(boxes) < leaves:
        k = int(rng.integers(len(boxes)))
        a = int(rng.integers(3))
        lo, hi = boxes[k]
        s = lo[a] + (hi[a] - lo[a]) * rng.uniform(0.3, 0.7)
        node = leaf_node[k]
        upper = boxes[k].copy()
        upper[0, a] = s
        boxes[k] = boxes[k].copy()
        boxes[k][1, a] = s
        boxes.append(upper)
        left, right = len(axis), len(axis) + 1
        axis += [LEAF, LEAF]
        split += [0.0, 0.0]
        child += [[k, -1], [len(boxes) - 1, -1]]
        axis[node], split[node], child[node] = a, s, [left, right]
        leaf_node[k], leaf_node[len(boxes) - 1] = left, right
    return ChunkTree(np.array(axis, np.int8), np.array(split), np.array(child, np.int32), np.array(boxes))


def root_box(scene) -> np.ndarray:
    b = scene.bounds()
    grow = 1e-4 * scene.diagonal()
    return np.stack([b[0] - grow, b[1] + grow])


def bbox_chunks(scene, tree: ChunkTree) -> list[ChunkGeometry]:
    """Each chunk's triangles: those whose bounding box meets the chunk box
    grown by INSERT_MARGIN (a superset of the exact overlap)."""
    margin = INSERT_MARGIN * scene.diagonal()
    corners = scene.vertices[scene.triangles].astype(np.float64)
    lo, hi = corners.min(axis=1), corners.max(axis=1)
    out = []
    for box in tree.boxes:
        sel = np.flatnonzero(np.all(lo <= box[1] + margin, axis=1) & np.all(hi >= box[0] - margin, axis=1))
        used, local = np.unique(scene.triangles[sel], return_inverse=True)
        out.append(ChunkGeometry(scene.vertices[used], local.reshape(-1, 3).astype(np.int32),
                                 scene.tri_material[sel], sel.astype(np.int32),
                                 scene.uvs[used] if len(scene.uvs) else None,
                                 normals=scene.normals[used] if len(scene.normals) else None))
    return out


class MemoryChunks:
    """A chunk provider held in memory (what OSPPM reads from a store)."""

    def __init__(self, scene, tree: ChunkTree):
        self.header, self.tree = scene.header(), tree
        self.chunks = bbox_chunks(scene, tree)
        # Rough resident size: arrays plus Embree's ~2x copy and BVH.
        self.chunk_memory = np.array([3 * g.nbytes + 1 for g in self.chunks], np.float64)
        self.loads = []

    def load(self, k: int):
        self.loads.append(k)
        return self.chunks[k]
