"""Which lights reach each part of the scene, learned from the photons.

A light tree bounds what a light could deliver to a hit point, but not
whether a wall stands between them: in a building whose rooms hold 5 of
600 lights, nearly all of the tree's choices from a room's floor are lamps
of the rooms around it. A photon mapper already knows better. Each photon
carries the index of the light that emitted it (`RayBatch.pixel` holds
-1 - light for photon paths), and its first hit is a point that light
sees. So each first hit adds the photon's flux to its light's entry in a
cell of a hash grid keyed by position and by the axis the surface faces
(the two sides of a wall are different cells). Whether or not the hit
deposits: with shadow rays for direct light, first hits do not.

A hit point's shadow ray then picks its light from a defensive mixture:
with probability a the light tree's choice, else a light of its cell in
proportion to its learned flux. The probability of the light chosen is
a p_tree + (1 - a) p_cell, evaluated for the sample from the same table
it was drawn from, so the estimate stays unbiased whatever the table
holds: every light that can light the hit point keeps at least a p_tree
> 0. (Eye passes read a table no photon writes meanwhile: see `frozen`.) The tree's share a falls from 1 in an
empty cell towards MIN_TREE_SHARE as the cell's photons accumulate.

Each cell keeps SLOTS lights. A light arriving at a full cell takes the
slot of the one with least flux, whose flux moves to the cell's `rest`:
flux from lights the cell does not name, which the mixture hands to the
tree (a cell lit by many lights, as a plane under forty lamps, then
leaves most choices to the tree instead of starving the lights it lost).
Cells are found by linear probing; a first hit whose cell finds no room
within PROBES slots is dropped. Memory is fixed at construction.

With `frozen`, eye passes read a copy taken (`trace.freeze_light_cache`) at the start of
each eye iteration, while the photons teach the live table: an iteration's
choices then depend on the photons of the iterations before it, not on
how far this iteration's photons have got, so a chunked render chooses
as the unchunked one does (the same seed, the same image).
"""
from __future__ import annotations

import math

import numba as nb
import numpy as np

from dosppm_core.kernels.bsdf import is_specular
from dosppm_core.kernels.paths import hit_setup

SLOTS = 8
PROBES = 32
CELLS_PER_DIAGONAL = 128        # default cell edge: the scene's diagonal over this
MIN_TREE_SHARE = 0.1
HALF_TREE_PHOTONS = 8.0         # photons in a cell at which the tree's share is half way down
CELL_BYTES = 8 + 4 + 4 + SLOTS * (4 + 4)
_MASK20 = (1 << 20) - 1


class LightCache:
    """The learned table of one process (every chunk it traces). `arrays`
    is what the kernels take; `empty()` learns nothing and leaves every
    choice to the light tree."""

    def __init__(self, bounds, memory_bytes: int, cell: float | None = None, frozen: bool = False):
        bounds = np.asarray(bounds, np.float64)
        h = float(cell) if cell else float(np.linalg.norm(bounds[1] - bounds[0])) / CELLS_PER_DIAGONAL
        per_cell = CELL_BYTES * (2 if frozen else 1)
        cells = 1 << max(0, int(math.log2(max(1, memory_bytes // per_cell))))
        self.keys = np.full(cells if memory_bytes >= per_cell else 0, -1, np.int64)
        n = self.keys.shape[0]
        self.count = np.zeros(n, np.int32)
        self.rest = np.zeros(n, np.float32)
        self.light = np.full((n, SLOTS), -1, np.int32)
        self.flux = np.zeros((n, SLOTS), np.float32)
        self.grid = np.array([*(bounds[0] - h), 1.0 / max(h, 1e-30)])
        self.read = tuple(a.copy() for a in self.arrays()) if frozen else self.arrays()

    @classmethod
    def empty(cls) -> LightCache:
        return cls(np.zeros((2, 3)), 0)

    def arrays(self) -> tuple:
        """The live table, which the photons teach."""
        return self.keys, self.count, self.rest, self.light, self.flux, self.grid


def share_of_memory(memory_bytes: float, largest_chunk: float, wanted: int) -> tuple[float, int]:
    """(bytes for chunks, bytes for the light cache) out of a process's
    `memory_bytes`: the cache counts in the chunk budget, and gives way
    (down to nothing: the tree alone) so that the largest chunk still fits."""
    cache = int(max(0.0, min(float(wanted), memory_bytes - largest_chunk)))
    return memory_bytes - cache, cache


@nb.njit(inline="always", cache=True, error_model="numpy")
def cell_key(grid, p0, p1, p2, n0, n1, n2):
    """The cell of point p on a surface facing n: its grid cell and
    the axis and sign the normal is nearest to (20 bits a grid axis)."""
    ix = math.floor((p0 - grid[0]) * grid[3]) & _MASK20
    iy = math.floor((p1 - grid[1]) * grid[3]) & _MASK20
    iz = math.floor((p2 - grid[2]) * grid[3]) & _MASK20
    a0, a1, a2 = abs(n0), abs(n1), abs(n2)
    if a0 >= a1 and a0 >= a2:
        d = 0 if n0 > 0.0 else 1
    elif a1 >= a2:
        d = 2 if n1 > 0.0 else 3
    else:
        d = 4 if n2 > 0.0 else 5
    return (ix << 43) | (iy << 23) | (iz << 3) | d


@nb.njit(inline="always", cache=True, error_model="numpy")
def _home(key, n):
    # splitmix64's finalizer: every bit of the key moves the low bits (a
    # plain multiply leaves them to the key's low bits, its z and facing).
    h = np.uint64(key)
    h = (h ^ (h >> np.uint64(30))) * np.uint64(0xBF58476D1CE4E5B9)
    h = (h ^ (h >> np.uint64(27))) * np.uint64(0x94D049BB133111EB)
    h = h ^ (h >> np.uint64(31))
    # int64 out: numba makes uint64 mixed with int64 a float
    return np.int64(h & np.uint64(n - 1))


@nb.njit(inline="always", cache=True, error_model="numpy")
def find_cell(keys, key, claim=False):
    """The row holding `key` (with `claim`, claimed if new), or -1: not
    there, or no room within PROBES rows of its home."""
    n = keys.shape[0]
    if n == 0:
        return -1
    s = _home(key, n)
    for _ in range(PROBES):
        k = keys[s]
        if k == key:
            return s
        if k < 0:
            if not claim:
                return -1
            keys[s] = key
            return s
        s = (s + 1) & (n - 1)
    return -1


@nb.njit(inline="always", cache=True, error_model="numpy")
def _add(rest, light, flux, s, li, f):
    """Light li's flux f into row s; in a full row it takes the slot of the
    least flux, which moves to the row's rest."""
    low = 0
    for k in range(SLOTS):
        if light[s, k] == li or light[s, k] < 0:
            light[s, k] = li
            flux[s, k] += f
            return
        if flux[s, k] < flux[s, low]:
            low = k
    rest[s] += flux[s, low]
    light[s, low] = li
    flux[s, low] = f


@nb.njit(cache=True, error_model="numpy")
def learn_first_hits(cache, direction, weight, depth, pixel, prim, u, v, surf):
    """Add each photon path's first surface hit (depth 0, a photon: pixel
    < 0) at a non-specular surface it can light; returns how many found
    no room."""
    keys, count, rest, light, flux, grid = cache
    verts, tris, tri_mat, kinds, _refl, _emit, _ior, _rough, two_sided, _eps, _bsdf = surf
    dropped = 0
    if keys.shape[0] == 0:
        return dropped
    for i in range(prim.shape[0]):
        tri = prim[i]
        if depth[i] != 0 or pixel[i] >= 0 or tri < 0:
            continue
        p0, p1, p2, n0, n1, n2, _w0, _w1, _w2, m, kind, front = hit_setup(
            verts, tris, tri_mat, kinds, tri, u[i], v[i], direction[i, 0], direction[i, 1], direction[i, 2])
        if is_specular(kind) or not (front or two_sided[m]):
            continue
        s = 1.0 if front else -1.0
        row = find_cell(keys, cell_key(grid, p0, p1, p2, s * n0, s * n1, s * n2), True)
        if row < 0:
            dropped += 1
            continue
        count[row] += 1
        _add(rest, light, flux, row, -1 - pixel[i], (weight[i, 0] + weight[i, 1] + weight[i, 2]) / 3.0)
    return dropped


@nb.njit(inline="always", cache=True, error_model="numpy")
def read_cell(cache, p0, p1, p2, n0, n1, n2):
    """(row, the tree's share a, the row's total flux) for hit point p
    (normal n): a is the tree's part of the defensive mixture plus the
    flux of lights the cell lost. With no cell, or nothing in it: (-1, 1, 0)."""
    keys, count, rest, light, flux, grid = cache
    row = find_cell(keys, cell_key(grid, p0, p1, p2, n0, n1, n2))
    if row < 0:
        return -1, 1.0, 0.0
    total = 0.0
    for k in range(SLOTS):
        if light[row, k] >= 0:
            total += max(0.0, np.float64(flux[row, k]))
    if not total > 0.0:
        return -1, 1.0, 0.0
    c = np.float64(count[row])
    share = MIN_TREE_SHARE + (1.0 - MIN_TREE_SHARE) * HALF_TREE_PHOTONS / (HALF_TREE_PHOTONS + c)
    lost = np.float64(rest[row]) / (np.float64(rest[row]) + total)
    return row, share + (1.0 - share) * lost, total


@nb.njit(inline="always", cache=True, error_model="numpy")
def cell_pmf(cache, row, total, li):
    """Probability of light li under row `row` (of total flux `total`)."""
    if row < 0:
        return 0.0
    light, flux = cache[3], cache[4]
    p = 0.0
    for k in range(SLOTS):
        if light[row, k] == li:
            p += max(0.0, np.float64(flux[row, k]))
    return p / total


@nb.njit(inline="always", cache=True, error_model="numpy")
def pick_in_cell(cache, row, total, u):
    """A light of row `row` in proportion to its flux. The lights are taken
    in the order of their indices, not of their slots (which depends on the
    order the photons arrived in), so the same table and u pick the same
    light however the photons were traced."""
    light, flux = cache[3], cache[4]
    acc, prev = 0.0, -1
    for _ in range(SLOTS):
        nxt, f_nxt = -1, 0.0
        for k in range(SLOTS):
            li, f = light[row, k], max(0.0, np.float64(flux[row, k]))
            if li > prev and f > 0.0 and (nxt < 0 or li < nxt):
                nxt, f_nxt = li, f
        if nxt < 0:
            break
        acc, prev = acc + f_nxt, nxt
        if u * total < acc:
            return nxt
    return prev
