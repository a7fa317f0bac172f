"""Automatic scene subdivision into chunks (Günther & Grosch §4.1, stages 1-4).

1. Binning: count triangles per cell of a uniform grid over the root box,
   by centroid, streaming over the source's blocks.
2. kd-tree, top down: split at the bin boundary (any axis) that best
   balances the two halves' counts, while a node's memory estimate exceeds
   the budget (or, with `chunks=C`, split the fullest leaf until there are
   C). Split planes are exact bin boundaries, so chunk boxes share their
   faces bit for bit.
3. Portals: the rectangles where neighbouring chunk boxes touch.
4. Insertion: every triangle goes into every chunk whose box, grown by
   `INSERT_MARGIN` x diagonal, it really overlaps (an exact separating-axis
   test), via per-chunk spill files; then each chunk's vertices are
   de-duplicated and its file written. Triangles straddling a portal are
   duplicated, so a chunk may come out over the budget: it is then split
   again from its own spill file, until every chunk on disk fits.

Stage 5 (the BVH) is built when a chunk is loaded (`chunked.ChunkView`).
At no point is more than one source block or one chunk held in memory.
"""
from __future__ import annotations

import heapq
import os
import shutil
import time
from dataclasses import dataclass, field

import numba
import numpy as np

from dosppm_core.chunks import store as chunkstore
from dosppm_core.chunks.portals import INSERT_MARGIN
from dosppm_core.chunks.store import ChunkGeometry
from dosppm_core.chunks.textures import attach_textures, store_header
from dosppm_core.chunks.tree import LEAF, ChunkTree
from dosppm_core.scene.loaders import load_source
from dosppm_core.scene.model import SceneError
from dosppm_core.scene.soup import BLOCK

ROOT_MARGIN = 1e-4       # root box = header bounds grown by this x diagonal on every side
DEFAULT_GRID = 32768     # bins in the uniform grid (the paper: 4k to 262k)
MAX_DEPTH = 60           # ChunkTree.validate refuses deeper trees

# Memory model of a loaded chunk: the arrays as stored, plus the padded
# vertex copy that Embree reads in place (12 B per vertex; accel.py shares
# the triangle array with Embree, copying nothing else) and the BVH.
# Measured as the peak RSS growth (VmHWM after resetting it through
# /proc/self/clear_refs) of building an `Accelerator` in a fresh process,
# Embree 4.4 from embreex 4.4.0.post1, robust scene flag, on random
# overlapping triangles (the worst case seen): 99 B per triangle at 1M
# triangles, 103 B at 2M. The peak exceeds the final size (builder scratch),
# and the budget must hold at the peak.
# `harness.embree_memory.measure_embree_bytes_per_triangle()` repeats the triangle measurement.
EMBREE_BYTES_PER_TRIANGLE = 110
EMBREE_BYTES_PER_VERTEX = 12
STORED_BYTES_PER_TRIANGLE = 12 + 4 + 4   # triangles, tri_material, global_id
STORED_BYTES_PER_VERTEX = 12
STORED_BYTES_PER_UV = 8                  # a textured chunk's uv per vertex
STORED_BYTES_PER_NORMAL = 12             # a smooth scene's chunk's vertex normal
# Before insertion only triangle counts are known; a closed mesh has about
# half a vertex per triangle. Guessing low never over-splits: a chunk that
# comes out too big is split again after insertion.
GUESS_VERTICES_PER_TRIANGLE = 0.5

RECORD = np.dtype([("corners", "<f4", (3, 3)), ("material", "<i4"), ("global_id", "<i4")])
# The record of a source with texture coordinates: its corners' uv too.
RECORD_UV = np.dtype(RECORD.descr + [("uv", "<f4", (3, 2))])
NORMAL_FIELD = ("normal", "<f4", (3, 3))    # a smooth scene's corners' vertex normals


def record_dtype(uv: bool, normals: bool = False) -> np.dtype:
    return np.dtype((RECORD_UV if uv else RECORD).descr + ([NORMAL_FIELD] if normals else []))

# Working memory per triangle of a source block during insertion: the block
# read (40 B), its records (44), the (triangle, chunk) overlap pairs and
# their sorted copies (44), the records copied out per chunk (44), index
# arrays (~24). Binning needs less. `subdivide(memory_bytes=...)` sizes
# blocks with it, so the subdivider's memory is set, not the scene's size:
# one block, or one chunk being written (about 1.5x the chunk budget).
BLOCK_BYTES_PER_TRIANGLE = 200
MIN_BLOCK = 4096


def block_for_memory(memory_bytes: int) -> int:
    """Triangles per source block for a working memory of `memory_bytes`."""
    return max(MIN_BLOCK, int(memory_bytes) // BLOCK_BYTES_PER_TRIANGLE)


def chunk_memory_bytes(triangles: int, vertices: int, uv: bool = False, normals: bool = False) -> int:
    """Estimated resident bytes of a loaded chunk, BVH build peak included."""
    per_vertex = STORED_BYTES_PER_VERTEX + EMBREE_BYTES_PER_VERTEX + (STORED_BYTES_PER_UV if uv else 0) \
        + (STORED_BYTES_PER_NORMAL if normals else 0)
    return int((STORED_BYTES_PER_TRIANGLE + EMBREE_BYTES_PER_TRIANGLE) * triangles + per_vertex * vertices)


def _guess_memory(count: int) -> int:
    return chunk_memory_bytes(count, int(count * GUESS_VERTICES_PER_TRIANGLE))


# -- stage 1: binning ----------------------------------------------------------
@dataclass
class Grid:
    """The uniform grid over the root box and its per-bin triangle counts.
    `planes[a]` are the bin boundaries along axis a (float64, planes[a][0]
    and planes[a][-1] the root box's faces); `prefix` is the summed-volume
    table of `counts`, so any box of bins is counted in O(1)."""
    box: np.ndarray          # float64 (2, 3)
    shape: tuple
    planes: list
    counts: np.ndarray       # int64 shape
    prefix: np.ndarray       # int64 shape + 1

    def count(self, lo, hi) -> int:
        P = self.prefix
        (x0, y0, z0), (x1, y1, z1) = lo, hi
        return int(P[x1, y1, z1] - P[x0, y1, z1] - P[x1, y0, z1] - P[x1, y1, z0]
                   + P[x0, y0, z1] + P[x0, y1, z0] + P[x1, y0, z0] - P[x0, y0, z0])

    def bin_box(self, lo, hi) -> np.ndarray:
        return np.array([[self.planes[a][lo[a]] for a in range(3)],
                         [self.planes[a][hi[a]] for a in range(3)]])


def root_box(header) -> np.ndarray:
    """The header's bounds grown by ROOT_MARGIN x diagonal on every side, so
    no geometry lies on the root box's outer faces."""
    diag = header.diagonal()
    if not np.isfinite(diag) or diag <= 0:
        raise SceneError(f"scene {header.name}: bounds {header.bounds.tolist()} have no extent")
    b = np.asarray(header.bounds, np.float64)
    return np.stack([b[0] - ROOT_MARGIN * diag, b[1] + ROOT_MARGIN * diag])


def grid_shape(extent, bins: int) -> tuple:
    """(nx, ny, nz) with about `bins` cells, per axis proportional to the
    extent (near-cubic cells); a thin axis gets one cell and its share goes
    to the others."""
    extent = np.asarray(extent, np.float64)
    free = [a for a in range(3)]
    while True:
        cell = (np.prod(extent[free]) / bins) ** (1.0 / len(free))
        thin = [a for a in free if extent[a] < cell]
        if not thin or len(thin) == len(free):
            break
        free = [a for a in free if a not in thin]
    return tuple(max(1, int(round(extent[a] / cell))) if a in free else 1 for a in range(3))


def bin_triangles(source, bins: int, block: int = BLOCK) -> Grid:
    box = root_box(source.header)
    shape = grid_shape(box[1] - box[0], bins)
    planes = [box[0, a] + (box[1, a] - box[0, a]) * (np.arange(shape[a] + 1) / shape[a])
              for a in range(3)]
    for a in range(3):
        planes[a][0], planes[a][-1] = box[0, a], box[1, a]
        if not np.all(np.diff(planes[a]) > 0):
            raise SceneError(f"grid of {bins} bins too fine for the scene's extent along axis {'xyz'[a]}")
    counts = np.zeros(shape, np.int64)
    scale = np.array(shape, np.float64) / (box[1] - box[0])
    for _first, corners, _material in source.blocks(block):
        _count_centroids(corners, box[0], scale, counts)
    prefix = np.zeros(tuple(s + 1 for s in shape), np.int64)
    prefix[1:, 1:, 1:] = counts.cumsum(0).cumsum(1).cumsum(2)
    return Grid(box, shape, planes, counts, prefix)


@numba.njit(cache=True)
def _count_centroids(corners, lo, scale, counts):
    idx = np.empty(3, np.int64)
    for i in range(corners.shape[0]):
        for a in range(3):
            c = (np.float64(corners[i, 0, a]) + corners[i, 1, a] + corners[i, 2, a]) / 3.0
            k = int(np.floor((c - lo[a]) * scale[a]))
            idx[a] = min(max(k, 0), counts.shape[a] - 1)
        counts[idx[0], idx[1], idx[2]] += 1


# -- stage 2: the kd-tree -------------------------------------------------------
@dataclass
class _Node:
    lo: tuple                  # bin range [lo, hi) per axis
    hi: tuple
    count: int                 # triangles by centroid
    depth: int
    axis: int = LEAF
    split_bin: int = -1
    children: tuple = ()


def best_split(grid: Grid, lo, hi):
    """(axis, bin boundary) minimising |count_lower - count_upper| over all
    three axes (§4.1), or None for a single bin. Ties go to the longer axis,
    then to the boundary nearest the middle, so empty space is halved."""
    total = grid.count(lo, hi)
    best, best_key = None, None
    for a in range(3):
        if hi[a] - lo[a] < 2:
            continue
        ts = np.arange(lo[a] + 1, hi[a])
        lower = np.array([grid.count(lo, _with(hi, a, t)) for t in ts])
        diff = np.abs(2 * lower - total)
        planes = grid.planes[a]
        extent = planes[hi[a]] - planes[lo[a]]
        off_middle = np.abs(planes[ts] - 0.5 * (planes[lo[a]] + planes[hi[a]])) / extent
        i = np.lexsort((off_middle, diff))[0]
        key = (int(diff[i]), -extent, float(off_middle[i]))
        if best_key is None or key < best_key:
            best, best_key = (a, int(ts[i])), key
    return best


def _with(v, a, value):
    v = list(v)
    v[a] = value
    return tuple(v)


class KdBuilder:
    """The kd-tree as mutable nodes over grid bins (stage 2), split further
    after insertion when a chunk turns out too big."""

    def __init__(self, grid: Grid):
        self.grid = grid
        self.nodes = [_Node((0, 0, 0), grid.shape, grid.count((0, 0, 0), grid.shape), 0)]

    def split(self, n: int) -> tuple[int, int] | None:
        """Split leaf n at its best boundary; the two new leaves, or None."""
        node = self.nodes[n]
        choice = best_split(self.grid, node.lo, node.hi)
        if choice is None:
            return None
        if node.depth >= MAX_DEPTH:
            raise SceneError(f"kd-tree deeper than {MAX_DEPTH} levels at {self.where(n)}; "
                             f"use a coarser --grid")
        a, t = choice
        kids = []
        for lo, hi in ((node.lo, _with(node.hi, a, t)), (_with(node.lo, a, t), node.hi)):
            kids.append(len(self.nodes))
            self.nodes.append(_Node(lo, hi, self.grid.count(lo, hi), node.depth + 1))
        node.axis, node.split_bin, node.children = a, t, tuple(kids)
        return kids[0], kids[1]

    def leaves(self) -> list[int]:
        """Leaf nodes in depth-first order (the final chunk numbering)."""
        out, stack = [], [0]
        while stack:
            n = stack.pop()
            if self.nodes[n].axis == LEAF:
                out.append(n)
            else:
                stack += [self.nodes[n].children[1], self.nodes[n].children[0]]
        return out

    def box(self, n: int) -> np.ndarray:
        return self.grid.bin_box(self.nodes[n].lo, self.nodes[n].hi)

    def where(self, n: int) -> str:
        b = self.box(n)
        return f"box {np.round(b[0], 6).tolist()}-{np.round(b[1], 6).tolist()}"

    def tree(self, leaves: list[int] | None = None) -> ChunkTree:
        """The `ChunkTree` (chunk k = leaves[k], default depth-first order)."""
        leaves = self.leaves() if leaves is None else leaves
        chunk_of = {n: k for k, n in enumerate(leaves)}
        # Nodes are only ever added below leaves, so every node is in the
        # tree and node n is row n (the root stays row 0).
        axis = np.full(len(self.nodes), LEAF, np.int8)
        split = np.zeros(len(self.nodes))
        child = np.zeros((len(self.nodes), 2), np.int32)
        for n, node in enumerate(self.nodes):
            if node.axis == LEAF:
                child[n] = (chunk_of[n], -1)
            else:
                axis[n], split[n] = node.axis, self.grid.planes[node.axis][node.split_bin]
                child[n] = node.children
        boxes = np.array([self.box(n) for n in leaves]).reshape(-1, 2, 3)
        return ChunkTree(axis, split, child, boxes)


def build_kdtree(grid: Grid, budget_bytes: int | None, chunks: int | None) -> KdBuilder:
    """Stage 2: split while a node's estimate exceeds the budget, or (given
    `chunks`) split the fullest splittable leaf until there are that many."""
    kd = KdBuilder(grid)
    if chunks is not None:
        _split_to_count(kd, chunks)
    else:
        _split_to_budget(kd, budget_bytes)
    return kd


def _split_to_count(kd: KdBuilder, chunks: int) -> None:
    heap, leaves = [(-kd.nodes[0].count, 0)], 1
    while leaves < chunks:
        if not heap:
            raise SceneError(f"cannot cut the scene into {chunks} chunks with a grid of "
                             f"{kd.grid.shape}; use a finer --grid")
        _neg, n = heapq.heappop(heap)
        kids = kd.split(n)
        if kids is not None:     # a single bin stays a leaf: try the next fullest
            leaves += 1
            for k in kids:
                heapq.heappush(heap, (-kd.nodes[k].count, k))


def _split_to_budget(kd: KdBuilder, budget_bytes: int) -> None:
    stack = [0]
    while stack:
        n = stack.pop()
        need = _guess_memory(kd.nodes[n].count)
        if need <= budget_bytes:
            continue
        kids = kd.split(n)
        if kids is None:
            raise _too_small(budget_bytes, kd, n, need)
        stack += list(kids)


def _too_small(budget_bytes, kd: KdBuilder, n: int, need: int) -> SceneError:
    node = kd.nodes[n]
    return SceneError(f"budget {format_bytes(budget_bytes)} too small for even one grid cell of "
                      f"{node.count:,} triangles at {kd.where(n)} (needs about {format_bytes(need)}); "
                      f"raise --budget or use a finer --grid")


def format_bytes(n) -> str:
    n = float(n)
    for unit in ("B", "KiB", "MiB", "GiB"):
        if n < 1024 or unit == "GiB":
            return f"{n:.0f} {unit}" if unit == "B" else f"{n:.1f} {unit}"
        n /= 1024


# -- stage 3: portals ---------------------------------------------------------
def find_portals(tree: ChunkTree) -> chunkstore.Portals:
    return chunkstore.Portals.of_tree(tree)


# -- stage 4: exact triangle-box overlap -------------------------------------
@numba.njit(cache=True)
def _separated(lx, ly, lz, v, half) -> bool:
    """Is the axis L = (lx, ly, lz) separating the triangle v (corners
    relative to the box centre) from the box of half-sizes `half`?"""
    p0 = lx * v[0, 0] + ly * v[0, 1] + lz * v[0, 2]
    p1 = lx * v[1, 0] + ly * v[1, 1] + lz * v[1, 2]
    p2 = lx * v[2, 0] + ly * v[2, 1] + lz * v[2, 2]
    r = half[0] * abs(lx) + half[1] * abs(ly) + half[2] * abs(lz)
    return min(p0, p1, p2) > r or max(p0, p1, p2) < -r


@numba.njit(cache=True)
def triangle_box_overlap(tri, lo, hi, margin) -> bool:
    """Does the closed triangle `tri` (3, 3) meet the closed box [lo - margin,
    hi + margin]? Akenine-Möller's separating-axis test in float64: the box's
    three normals, the triangle's normal, and the nine edge x box-axis
    crosses. Touching counts as overlapping."""
    v = np.empty((3, 3))
    half = np.empty(3)
    for a in range(3):
        c = 0.5 * (lo[a] + hi[a])
        half[a] = 0.5 * (hi[a] - lo[a]) + margin
        for j in range(3):
            v[j, a] = tri[j, a] - c
    for a in range(3):
        if min(v[0, a], v[1, a], v[2, a]) > half[a] or max(v[0, a], v[1, a], v[2, a]) < -half[a]:
            return False
    for j in range(3):
        ex, ey, ez = v[(j + 1) % 3, 0] - v[j, 0], v[(j + 1) % 3, 1] - v[j, 1], v[(j + 1) % 3, 2] - v[j, 2]
        # cross(unit x, e), cross(unit y, e), cross(unit z, e)
        if _separated(0.0, -ez, ey, v, half) or _separated(ez, 0.0, -ex, v, half) \
                or _separated(-ey, ex, 0.0, v, half):
            return False
    ax, ay, az = v[1, 0] - v[0, 0], v[1, 1] - v[0, 1], v[1, 2] - v[0, 2]
    bx, by, bz = v[2, 0] - v[0, 0], v[2, 1] - v[0, 1], v[2, 2] - v[0, 2]
    return not _separated(ay * bz - az * by, az * bx - ax * bz, ax * by - ay * bx, v, half)


@numba.njit(cache=True)
def overlap_matrix(corners, boxes, margin):
    """(n, c) bool: triangle i overlaps box k grown by margin (brute force,
    for tests and small inputs)."""
    out = np.zeros((corners.shape[0], boxes.shape[0]), np.bool_)
    tri = np.empty((3, 3))
    for i in range(corners.shape[0]):
        for j in range(3):
            for a in range(3):
                tri[j, a] = corners[i, j, a]
        for k in range(boxes.shape[0]):
            out[i, k] = triangle_box_overlap(tri, boxes[k, 0], boxes[k, 1], margin)
    return out


@numba.njit(cache=True)
def _overlap_pairs(axis, split, child, boxes, corners, margin):
    """(triangle, chunk) pairs of every exact overlap, found by descending
    the tree with each triangle's bounding box; chunks ascend per triangle."""
    n = corners.shape[0]
    cap = 2 * n + 16
    tris = np.empty(cap, np.int64)
    chunks = np.empty(cap, np.int32)
    m = 0
    stack = np.empty(2 * 64 + 2, np.int64)
    tri = np.empty((3, 3))
    for i in range(n):
        for j in range(3):
            for a in range(3):
                tri[j, a] = corners[i, j, a]
        sp = 1
        stack[0] = 0
        while sp > 0:
            sp -= 1
            node = stack[sp]
            a = axis[node]
            if a == LEAF:
                k = child[node, 0]
                if triangle_box_overlap(tri, boxes[k, 0], boxes[k, 1], margin):
                    if m == cap:
                        cap *= 2
                        tris = _grow(tris, cap)
                        chunks = _grow(chunks, cap)
                    tris[m], chunks[m] = i, k
                    m += 1
                continue
            s = split[node]
            tmin = min(tri[0, a], tri[1, a], tri[2, a])
            tmax = max(tri[0, a], tri[1, a], tri[2, a])
            if tmax >= s - margin:
                stack[sp] = child[node, 1]
                sp += 1
            if tmin <= s + margin:
                stack[sp] = child[node, 0]
                sp += 1
    return tris[:m], chunks[:m]


@numba.njit(cache=True)
def _grow(a, cap):
    out = np.empty(cap, a.dtype)
    out[:a.shape[0]] = a
    return out


# -- stage 4: insertion through spill files -----------------------------------
class Spill:
    """Per-leaf spill files of triangle records (corners, material, global
    id), appended block by block in global-id order."""

    def __init__(self, folder: str, dtype=RECORD):
        self.folder, self.dtype = folder, dtype
        os.makedirs(folder, exist_ok=True)

    def path(self, node: int) -> str:
        return os.path.join(self.folder, f"leaf-{node}.rec")

    def append(self, node: int, records: np.ndarray) -> None:
        with open(self.path(node), "ab") as f:
            records.tofile(f)

    def take(self, node: int) -> np.ndarray:
        """The node's records, removing its file."""
        p = self.path(node)
        if not os.path.exists(p):
            return np.empty(0, self.dtype)
        records = np.fromfile(p, self.dtype)
        os.remove(p)
        return records


def insert(records: np.ndarray, tree: ChunkTree, leaf_nodes: list[int], margin: float,
           spill: Spill) -> np.ndarray:
    """Append each record to the spill file of every leaf it overlaps;
    returns the number of leaves each record went to."""
    tris, chunks = _overlap_pairs(tree.axis, tree.split, tree.child, tree.boxes,
                                  records["corners"], margin)
    order = np.argsort(chunks, kind="stable")   # keeps global-id order per chunk
    tris, chunks = tris[order], chunks[order]
    cuts = np.flatnonzero(np.diff(chunks)) + 1
    for part in np.split(np.arange(len(chunks)), cuts):
        if len(part):
            spill.append(leaf_nodes[chunks[part[0]]], records[tris[part]])
    return np.bincount(tris, minlength=len(records))


def source_records(first: int, corners: np.ndarray, material: np.ndarray, uv=None, normals=None) -> np.ndarray:
    r = np.empty(len(corners), record_dtype(uv is not None, normals is not None))
    r["corners"], r["material"] = corners, material
    if uv is not None:
        r["uv"] = uv
    if normals is not None:
        r["normal"] = normals
    r["global_id"] = np.arange(first, first + len(corners))
    return r


def dedup_geometry(records: np.ndarray) -> ChunkGeometry:
    """Chunk-local arrays: vertices shared by bitwise-equal corners (and,
    with texture coordinates, equal uv: a seam keeps its two vertices; with
    vertex normals, equal normals: a crease keeps its two)."""
    nt = len(records)
    uv = "uv" in records.dtype.names
    smooth = "normal" in records.dtype.names
    bits = np.ascontiguousarray(records["corners"]).reshape(-1, 3).view("<u4")
    if uv:
        bits = np.concatenate([bits, np.ascontiguousarray(records["uv"]).reshape(-1, 2).view("<u4")], axis=1)
    if smooth:
        bits = np.concatenate([bits, np.ascontiguousarray(records["normal"]).reshape(-1, 3).view("<u4")], axis=1)
    order = np.lexsort(bits.T[::-1])
    sorted_bits = bits[order]
    new = np.ones(len(order), bool)
    new[1:] = np.any(sorted_bits[1:] != sorted_bits[:-1], axis=1)
    local = np.empty(len(order), np.int32)
    local[order] = np.cumsum(new) - 1
    unique = np.ascontiguousarray(sorted_bits[new]).view("<f4")
    return ChunkGeometry(np.ascontiguousarray(unique[:, :3]), local.reshape(nt, 3),
                         records["material"].astype(np.int32), records["global_id"].astype(np.int32),
                         np.ascontiguousarray(unique[:, 3:5]) if uv else None,
                         normals=np.ascontiguousarray(unique[:, -3:]) if smooth else None)


# -- the whole pipeline ---------------------------------------------------------
@dataclass
class SubdivisionReport:
    path: str
    chunk_count: int
    chunk_triangles: np.ndarray
    source_triangles: int
    grid: tuple
    seconds: dict = field(default_factory=dict)   # per stage

    @property
    def duplicated_fraction(self) -> float:
        """Extra triangle copies made by straddling portals, per source triangle."""
        return float(self.chunk_triangles.sum() - self.source_triangles) / max(self.source_triangles, 1)


def subdivide(source, out: str, budget_bytes: int | None = None, grid: int = DEFAULT_GRID,
              chunks: int | None = None, block: int = BLOCK,
              memory_bytes: int | None = None) -> SubdivisionReport:
    """Subdivide `source` (a `TriangleSource`) into a chunk store at `out`.
    Give a memory budget per chunk, or `chunks` to force that many (a budget
    given too is then checked, not used to split). `memory_bytes` sizes the
    source blocks (`block_for_memory`) instead of `block`."""
    _check_arguments(source, budget_bytes, grid, chunks)
    if memory_bytes is not None:
        block = block_for_memory(memory_bytes)
    chunkstore.check_target(out)
    seconds = {}
    t = time.perf_counter()
    g = bin_triangles(source, grid, block)
    seconds["binning"], t = time.perf_counter() - t, time.perf_counter()
    kd = build_kdtree(g, budget_bytes, chunks)
    seconds["kd-tree"], t = time.perf_counter() - t, time.perf_counter()
    partial = chunkstore.partial_path(out)
    shutil.rmtree(partial, ignore_errors=True)
    try:
        spill = Spill(os.path.join(partial, "spill"), record_dtype(_has_uv(source), _has_normals(source)))
        margin = INSERT_MARGIN * source.header.diagonal()
        _insert_source(source, kd, margin, spill, block)
        seconds["insertion"], t = time.perf_counter() - t, time.perf_counter()
        written = _finish_chunks(kd, spill, margin, partial, budget_bytes, chunks is not None,
                                 source.header)
        shutil.rmtree(spill.folder)
        seconds["chunk files"], t = time.perf_counter() - t, time.perf_counter()
        tree = kd.tree()
        portals = find_portals(tree)
        seconds["portals"] = time.perf_counter() - t
        entries = _rename_chunks(partial, kd.leaves(), written)
        digest = source.content_hash()
        key = chunkstore.store_key(digest, budget_bytes, grid, chunks)
        chunkstore.commit_store(partial, out, _manifest(source, digest, key, tree, portals,
                                                        entries, budget_bytes, grid, g, chunks))
    except BaseException:
        shutil.rmtree(partial, ignore_errors=True)
        raise
    counts = np.array([e["triangles"] for e in entries], np.int64)
    return SubdivisionReport(out, tree.chunk_count, counts, source.count, g.shape, seconds)


def _check_arguments(source, budget_bytes, grid, chunks) -> None:
    if budget_bytes is None and chunks is None:
        raise ValueError("give a memory budget per chunk or a chunk count")
    if budget_bytes is not None and budget_bytes <= 0:
        raise ValueError(f"budget must be positive, got {budget_bytes}")
    if chunks is not None and chunks < 1:
        raise ValueError(f"chunk count must be at least 1, got {chunks}")
    if grid < 1:
        raise ValueError(f"grid must have at least one bin, got {grid}")
    if source.count >= 2 ** 31:
        raise SceneError(f"{source.count:,} triangles: global ids are int32, at most 2^31 - 1")


def _has_uv(source) -> bool:
    """Whether a triangle source carries texture coordinates (`SceneSource`
    of a textured scene; soups have none)."""
    return bool(getattr(source, "has_uv", False))


def _has_normals(source) -> bool:
    """Whether a triangle source carries vertex normals (smooth meshes)."""
    return bool(getattr(source, "has_normals", False))


def _insert_source(source, kd: KdBuilder, margin: float, spill: Spill, block: int) -> None:
    """Stream the source through the tree into the leaves' spill files."""
    leaves = kd.leaves()
    tree = kd.tree(leaves)
    uv, smooth = _has_uv(source), _has_normals(source)
    for first, corners, material in source.blocks(block):
        corner_uv = source.corner_uv(first, len(corners)) if uv else None
        corner_n = source.corner_normals(first, len(corners)) if smooth else None
        copies = insert(source_records(first, corners, material, corner_uv, corner_n), tree, leaves, margin,
                        spill)
        if np.any(copies == 0):
            i = first + int(np.flatnonzero(copies == 0)[0])
            raise SceneError(f"scene {source.header.name}: triangle {i} lies outside the "
                             f"bounds given in its header {source.header.bounds.tolist()}")


def _finish_chunks(kd: KdBuilder, spill: Spill, margin: float, partial: str,
                   budget_bytes, forced: bool, header) -> dict:
    """Write each leaf's chunk file (as leaf-<node>.bin); a leaf over the
    budget is split and its records re-inserted into its two halves."""
    written = {}
    todo = kd.leaves()
    while todo:
        n = todo.pop()
        records = spill.take(n)
        geometry = attach_textures(dedup_geometry(records), header)
        need = chunk_memory_bytes(len(geometry.triangles), len(geometry.vertices), len(geometry.uv) > 0,
                                  len(geometry.normals) > 0) + geometry.texture_bytes
        if budget_bytes is not None and need > budget_bytes:
            if forced:
                raise SceneError(f"chunk at {kd.where(n)} needs {format_bytes(need)}, over the "
                                 f"budget {format_bytes(budget_bytes)}: ask for more chunks")
            kids = kd.split(n)
            if kids is None:
                raise _too_small(budget_bytes, kd, n, need)
            sub = _split_tree(kd, n)
            insert(records, sub, list(kids), margin, spill)
            todo += list(kids)
            continue
        entry = chunkstore.write_chunk_file(os.path.join(partial, f"leaf-{n}.bin"), geometry)
        entry["memory_bytes"] = need
        written[n] = entry
    return written


def _split_tree(kd: KdBuilder, n: int) -> ChunkTree:
    """The one split of node n as a tree of its own (chunks 0, 1 = its children)."""
    node = kd.nodes[n]
    return ChunkTree(np.array([node.axis, LEAF, LEAF], np.int8),
                     np.array([kd.grid.planes[node.axis][node.split_bin], 0.0, 0.0]),
                     np.array([[1, 2], [0, -1], [1, -1]], np.int32),
                     np.array([kd.box(k) for k in node.children]))


def _rename_chunks(partial: str, leaves: list[int], written: dict) -> list[dict]:
    entries = []
    for k, n in enumerate(leaves):
        name = chunkstore.chunk_file_name(k)
        os.rename(os.path.join(partial, f"leaf-{n}.bin"), os.path.join(partial, name))
        entries.append(dict(written[n], file=name))
    return entries


def _manifest(source, digest, key, tree, portals, entries, budget_bytes, bins, g: Grid,
              chunks) -> dict:
    return {"format": chunkstore.FORMAT, "version": chunkstore.FORMAT_VERSION, "key": key,
            "tree": tree.to_wire(), "portals": portals.to_wire(),
            "header": store_header(source.header).to_wire(), "source_hash": digest,
            "source_triangles": int(source.count), "budget_bytes": budget_bytes,
            "grid": list(g.shape), "grid_bins": int(bins), "chunks_forced": chunks,
            "insert_margin": INSERT_MARGIN * source.header.diagonal(),
            "memory_model": {"embree_bytes_per_triangle": EMBREE_BYTES_PER_TRIANGLE,
                             "embree_bytes_per_vertex": EMBREE_BYTES_PER_VERTEX},
            "chunks": entries}


# -- the store a render uses ------------------------------------------------------
def open_or_subdivide(source, cache_dir: str, budget=None, grid: int | None = None,
                      chunks: int | None = None) -> chunkstore.ChunkStore:
    """The store for (source, budget, grid, chunks) under `cache_dir`:
    reused when one with the same key is there and opens cleanly, made
    (replacing a stale or damaged one) otherwise."""
    grid = DEFAULT_GRID if grid is None else int(grid)
    budget = None if budget is None else int(budget)
    key = chunkstore.store_key(source.content_hash(), budget, grid, chunks)
    path = os.path.join(cache_dir, key)
    try:
        store = chunkstore.ChunkStore.open(path)
        if store.key == key:
            return store
    except chunkstore.StoreError:
        pass
    if os.path.isdir(path):
        shutil.rmtree(path)   # ours by construction: the name is the key
    os.makedirs(cache_dir, exist_ok=True)
    subdivide(source, path, budget_bytes=budget, grid=grid, chunks=chunks)
    return chunkstore.ChunkStore.open(path)


def open_render_store(scene: str, cache_dir: str, budget_bytes: int | None, chunks: int | None,
                      width: int | None = None, height: int | None = None,
                      params: dict | None = None) -> chunkstore.ChunkStore:
    """The chunk store to render `scene` from: the store itself when `scene`
    is one, otherwise the scene (built-in name, scene file or soup; a
    Mitsuba file with its `params`) subdivided into `chunks`, or at
    `budget_bytes`, and kept under `cache_dir` for the next render
    (`open_or_subdivide`; the parameters change the key). `width` and
    `height` override its camera's."""
    if chunkstore.is_store(scene):
        if params:
            raise SceneError(f"{scene}: parameters {', '.join(params)} given, but only a Mitsuba .xml "
                             f"file takes them")
        store = chunkstore.ChunkStore.open(scene)
    else:
        store = open_or_subdivide(load_source(scene, params), cache_dir, budget=budget_bytes, chunks=chunks)
    if width:
        store.header.camera.width = int(width)
    if height:
        store.header.camera.height = int(height)
    return store
