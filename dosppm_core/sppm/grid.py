"""The exact `grid` gather (pbrt-v4's SPPM layout, the "reverse"
organisation of the Photon Pipeline paper): hit points are inserted into
every cell of a hashed uniform grid that their radius overlaps, and each
photon visits only its own cell. No photon is lost: every hit point within
a photon's radius is registered in the photon's cell.

Cells are found by open addressing, so two cells hashing to one slot can
neither lend each other hit points nor count a hit point twice.
"""
import math
from typing import NamedTuple

import numba as nb
import numpy as np

from dosppm_core.kernels.anisotropic import frames_of, gather_f_framed, has_frame
from dosppm_core.kernels.materials import bsdf_rows, gather_tint
from dosppm_core.scene.model import ROUGH_DIELECTRIC

CELL_FACTOR = 2.0  # cell size in median radii
_P1, _P2, _P3 = 73856093, 19349663, 83492791


@nb.njit(cache=True, nogil=True, error_model="numpy")
def cell_key(ix, iy, iz):
    return (np.int64(ix) << 42) | (np.int64(iy) << 21) | np.int64(iz)


@nb.njit(cache=True, nogil=True, error_model="numpy")
def slot_of(ix, iy, iz, mask):
    return ((ix * _P1) ^ (iy * _P2) ^ (iz * _P3)) & mask


EMPTY = np.int64(-1)   # the key of a slot no cell occupies


@nb.njit(cache=True, nogil=True, error_model="numpy")
def _cell_ranges(hp_pos, hp_radius, lo, cell, dims):
    """Per hit point, the first and last cell (per axis) its radius
    overlaps, and the number of (hit point, cell) entries in all."""
    n = hp_pos.shape[0]
    lo_c = np.empty((n, 3), np.int64)
    hi_c = np.empty((n, 3), np.int64)
    total = 0
    for i in range(n):
        cnt = 1
        for k in range(3):
            a = int(math.floor((hp_pos[i, k] - hp_radius[i] - lo[k]) / cell))
            b = int(math.floor((hp_pos[i, k] + hp_radius[i] - lo[k]) / cell))
            lo_c[i, k] = min(max(a, 0), dims[k] - 1)
            hi_c[i, k] = min(max(b, 0), dims[k] - 1)
            cnt *= hi_c[i, k] - lo_c[i, k] + 1
        total += cnt
    return lo_c, hi_c, total


@nb.njit(cache=True, nogil=True, error_model="numpy")
def _register_cells(lo_c, hi_c, slot_key, start, entry_slot):
    """Find (by linear probing from its hash) or take a slot for every cell
    a hit point overlaps; count the entries per slot and turn the counts
    into list starts; note each entry's slot, in insertion order. Returns
    the longest list."""
    mask = slot_key.shape[0] - 1
    q = 0
    for i in range(lo_c.shape[0]):
        for ix in range(lo_c[i, 0], hi_c[i, 0] + 1):
            for iy in range(lo_c[i, 1], hi_c[i, 1] + 1):
                for iz in range(lo_c[i, 2], hi_c[i, 2] + 1):
                    key = cell_key(ix, iy, iz)
                    s = slot_of(ix, iy, iz, mask)
                    while slot_key[s] != key and slot_key[s] != EMPTY:
                        s = (s + 1) & mask
                    slot_key[s] = key
                    start[s + 1] += 1
                    entry_slot[q] = s
                    q += 1
    longest = 1
    for s in range(mask + 1):
        longest = max(longest, start[s + 1])
        start[s + 1] += start[s]
    return longest


@nb.njit(cache=True, nogil=True, error_model="numpy")
def _fill_entries(hp_pos, hp_radius, lo_c, hi_c, entry_slot, start, entry_hp, entry_pos):
    """Write each hit point's entries, in insertion order, at the next free
    place of their slots' lists."""
    fill = start[:-1].copy()
    q = 0
    for i in range(hp_pos.shape[0]):
        r2 = hp_radius[i] * hp_radius[i]
        for _ in range((hi_c[i, 0] - lo_c[i, 0] + 1) * (hi_c[i, 1] - lo_c[i, 1] + 1)
                       * (hi_c[i, 2] - lo_c[i, 2] + 1)):
            e = fill[entry_slot[q]]
            fill[entry_slot[q]] = e + 1
            entry_hp[e] = i
            for k in range(3):
                entry_pos[e, k] = hp_pos[i, k]
            entry_pos[e, 3] = r2
            q += 1


def build_grid(hp_pos, hp_radius, lo, cell, dims):
    """Returns (slot_start, entry_hp, slot_key, entry_pos, mask, longest):
    an open-addressed table of the cells holding hit points (no two cells
    share a slot), a CSR list per slot of the hit points registered there,
    and the longest list. The arrays are numpy's: numpy asks the kernel for
    huge pages, numba's allocator does not, and the page faults of a fresh
    8 MB numba array cost more here than filling it (20 ms per 36 MB)."""
    lo_c, hi_c, total = _cell_ranges(hp_pos, hp_radius, lo, cell, dims)
    # int32 slot offsets: half the cache footprint of the table the
    # gather indexes at random. 2^31 entries would be 60 GB of table.
    if total >= 2 ** 31:
        raise ValueError("grid gather: over 2^31 cell entries (radii too large for the grid)")
    # At most half the slots in use: there are no more occupied cells than
    # entries, nor than the grid has cells (often 10x fewer: the table then
    # stays in cache while it is built and probed).
    cells = min(total, int(np.prod(dims.astype(np.float64))))
    size = 1 << max(1, int(2 * cells - 1).bit_length())
    slot_key = np.full(size, EMPTY, np.int64)
    start = np.zeros(size + 1, np.int32)
    entry_slot = np.empty(total, np.int32)
    longest = _register_cells(lo_c, hi_c, slot_key, start, entry_slot)
    entry_hp = np.empty(total, np.int32)
    # Each entry carries its hit point's position and radius^2, so the
    # photon's distance test streams through the slot without a dependent
    # load of the hit point (the test rejects ~4 of 5 candidates).
    entry_pos = np.empty((total, 4), np.float32)
    _fill_entries(hp_pos, hp_radius, lo_c, hi_c, entry_slot, start, entry_hp, entry_pos)
    return start, entry_hp, slot_key, entry_pos, size - 1, int(longest)


# Columns of the packed hit-point rows: one 64-byte cache line per hit
# point holds everything a photon needs to test and splat it.
HP_POS, HP_MAT, HP_N, HP_OUT, HP_WEIGHT, HP_KIND, HP_ALPHA, HP_COLS = 0, 3, 4, 7, 10, 13, 14, 16


def pack_hit_points(hp, materials) -> np.ndarray:
    """(n, 16) float32 rows: position, material id, normal, outgoing
    direction, eye weight, material kind and GGX alpha."""
    rows = np.zeros((len(hp), HP_COLS), np.float32)
    rows[:, HP_POS:HP_POS + 3] = hp.position
    rows[:, HP_MAT] = hp.material
    rows[:, HP_N:HP_N + 3] = hp.normal
    rows[:, HP_OUT:HP_OUT + 3] = hp.outgoing
    rows[:, HP_WEIGHT:HP_WEIGHT + 3] = hp.weight
    rows[:, HP_KIND] = materials.kind[hp.material]
    rows[:, HP_ALPHA] = materials.roughness[hp.material]
    return rows


@nb.njit(cache=True, nogil=True, parallel=True, error_model="numpy")
def gather_photons(ph_pos, ph_in, ph_flux, start, entry_hp, slot_key, entry_pos, mask, longest,
                   lo, cell, dims, rows, frames, bsdf, acc):
    """Accumulate, per hit point, the photon count M and the BRDF-weighted flux Phi
    (eq. 3, times the eye path weight). numba has no atomics on the CPU, so each thread
    owns an accumulator (M, Phi) over a contiguous range of the (spatially sorted) photons,
    in `acc` (threads, hit points, 4), zeros when called (see _sum_threads). `bsdf`:
    materials.bsdf_rows, for the coloured kinds; `frames`: `anisotropic.frames_of`."""
    n = ph_pos.shape[0]
    threads = acc.shape[0]
    for t in nb.prange(threads):
        within = np.empty(longest, np.int32)   # the entries of a cell within the photon's reach
        for j in range(n * t // threads, n * (t + 1) // threads):
            px, py, pz = ph_pos[j, 0], ph_pos[j, 1], ph_pos[j, 2]
            ix = int(math.floor((px - lo[0]) / cell))
            iy = int(math.floor((py - lo[1]) / cell))
            iz = int(math.floor((pz - lo[2]) / cell))
            if ix < 0 or iy < 0 or iz < 0 or ix >= dims[0] or iy >= dims[1] or iz >= dims[2]:
                continue
            key = cell_key(ix, iy, iz)
            s = slot_of(ix, iy, iz, mask)
            while slot_key[s] != key and slot_key[s] != EMPTY:
                s = (s + 1) & mask
            if slot_key[s] == EMPTY:
                continue
            # The distance test rejects ~4 of 5 candidates at random: written
            # without a branch (every entry stored, the count advanced by the
            # test) it runs 1.4x faster than with one.
            k = 0
            for e in range(start[s], start[s + 1]):
                d0, d1, d2 = px - entry_pos[e, 0], py - entry_pos[e, 1], pz - entry_pos[e, 2]
                within[k] = entry_hp[e]
                k += np.int64(d0 * d0 + d1 * d1 + d2 * d2 <= entry_pos[e, 3])
            wi0, wi1, wi2 = ph_in[j, 0], ph_in[j, 1], ph_in[j, 2]
            # The hot loop stays free of calls taking arrays: numba would
            # reference-count every array argument of every call.
            for q in range(k):
                h = within[q]
                # A photon counts if it arrived from the front of the hit
                # point's surface. Its own surface's normal is not tested, as
                # in pbrt-v4: that test dropped the photons on the other wall
                # of every concave corner, and Sponza came out 2% dark.
                # (A rough dielectric's hit point also takes the photons
                # its transmission brings from behind.)
                n0, n1, n2 = rows[h, HP_N], rows[h, HP_N + 1], rows[h, HP_N + 2]
                kind = int(rows[h, HP_KIND])
                if n0 * wi0 + n1 * wi1 + n2 * wi2 <= 0.0 and kind != ROUGH_DIELECTRIC:
                    continue
                mat = int(rows[h, HP_MAT])
                f0, f1, f2 = gather_f_framed(has_frame(kind, bsdf, mat, frames, h), kind,
                                             np.float64(rows[h, HP_ALPHA]), bsdf, mat, frames, h, n0, n1, n2,
                                             rows[h, HP_OUT], rows[h, HP_OUT + 1], rows[h, HP_OUT + 2],
                                             wi0, wi1, wi2)
                # The hit point's reflectance (the older kinds') times eye
                # weight is the same for every photon: it multiplies the sum
                # once, at the end (materials.gather_tint).
                acc[t, h, 0] += 1.0
                acc[t, h, 1] += f0 * ph_flux[j, 0]
                acc[t, h, 2] += f1 * ph_flux[j, 1]
                acc[t, h, 3] += f2 * ph_flux[j, 2]


@nb.njit(cache=True, nogil=True, error_model="numpy")
def _sum_threads(acc, rows, mat_refl):
    """(M, Phi) per hit point from the threads' accumulators: the sum of
    f * flux times the hit point's tint (`gather_tint`) and eye weight."""
    total = acc[0].copy()
    for t in range(1, acc.shape[0]):
        total += acc[t]
    phi = np.empty((rows.shape[0], 3))
    for h in range(rows.shape[0]):
        mat = int(rows[h, HP_MAT])
        for k in range(3):
            phi[h, k] = total[h, 1 + k] * mat_refl[mat, k] * rows[h, HP_WEIGHT + k]
    return total[:, 0].copy(), phi


@nb.njit(cache=True, nogil=True)
def reach_box(pos, radius):
    """(2, 3) float64: the box of the points grown by the largest radius
    (one pass; numpy's axis reductions over (n, 3) take 10x longer)."""
    box = np.empty((2, 3))
    box[0, :] = np.inf
    box[1, :] = -np.inf
    rmax = 0.0
    for i in range(pos.shape[0]):
        rmax = max(rmax, radius[i])
        for k in range(3):
            box[0, k] = min(box[0, k], pos[i, k])
            box[1, k] = max(box[1, k], pos[i, k])
    box[0, :] -= rmax
    box[1, :] += rmax
    return box


def grid_layout(hp_pos: np.ndarray, hp_radius: np.ndarray):
    """Grid origin, cell size and dims: cells of twice the median radius
    over the hit points' box grown by the largest radius, so a typical hit
    point lands in at most 8 cells."""
    lo, hi = reach_box(hp_pos, hp_radius)
    cell = CELL_FACTOR * float(np.median(hp_radius))
    cell = max(cell, float((hi - lo).max()) / (1 << 20))   # keys hold 21 bits per axis
    dims = np.maximum(np.ceil((hi - lo) / cell).astype(np.int64), 1)
    return lo, cell, dims


class HitPointGrid(NamedTuple):
    """The hit points of one update registered in their cells, plus their
    packed rows: everything gather_photons reads besides the photons."""
    lo: np.ndarray
    cell: float
    dims: np.ndarray
    start: np.ndarray
    entry_hp: np.ndarray
    slot_key: np.ndarray
    entry_pos: np.ndarray
    mask: int
    longest: int
    rows: np.ndarray


def build_hit_point_grid(hp, hp_radius, materials) -> HitPointGrid:
    """The grid of hit points `hp` with radii `hp_radius` (serial, and
    free of the GIL: a caller can build it while it sorts the photons)."""
    lo, cell, dims = grid_layout(hp.position, hp_radius)
    table = build_grid(hp.position, hp_radius, lo, cell, dims)
    return HitPointGrid(lo, cell, dims, *table, pack_hit_points(hp, materials))


def gather_grid(ph, hp, hp_radius, materials, threads: int, grid: HitPointGrid | None = None):
    """Exact gather of photon deposits `ph` at hit points `hp` (through
    `grid` if the caller built it already). Returns (M, Phi) per hit point."""
    if len(hp) == 0 or len(ph.position) == 0:   # len(ph) of a GatherPhotons tuple is 4
        return np.zeros(len(hp)), np.zeros((len(hp), 3))
    g = grid if grid is not None else build_hit_point_grid(hp, hp_radius, materials)
    acc = np.zeros((max(1, threads), len(hp), 4))
    gather_photons(ph.position, ph.incoming, ph.flux, g.start, g.entry_hp, g.slot_key, g.entry_pos,
                   g.mask, g.longest, g.lo, g.cell, g.dims, g.rows, frames_of(hp), bsdf_rows(materials), acc)
    return _sum_threads(acc, g.rows, gather_tint(materials))
