"""The stochastic spatial hash gather (`hash`) of Hachisuka & Jensen 2010,
the photon store the DOSPPM paper used on its GPU server (Günther & Grosch
§2.1, §4.2).

Photons are binned into a grid of fixed resolution over the box of all hit
points grown by the largest radius (the paper: 512 x 128 x 512; the smallest
resolution goes to the box's shortest axis). Cell ids are hashed into a
table of `table_size` slots and only ONE photon per slot is kept, chosen
uniformly among the photons that fell into the slot; the collisions are
counted, and the kept photon stands for all of them with weight
`count` (the slot's photon count). For a hit point, the expected sum over
a slot is then exactly the sum over the slot's photons, so M (the expected
photon count) and Phi (the BRDF-weighted flux) are unbiased. The price is
variance: the photons lost to collisions (`hash_statistics`) slow the
convergence, which is why the paper batches ~1M photons per update (§4.3).

Each hit point visits the slots of all cells its radius sphere overlaps,
each slot once (two overlapped cells may share a slot), and tests the kept
photon's distance and BRDF exactly like the grid gather.

Selection. The kept photon is the one with the smallest priority, a
counter-based hash of (seed, photon position and direction bits). It is
uniform over seeds and independent of the photons' order (Morton
reordering changes nothing). A pick by rank from a hash of (seed, slot)
would not be: with the fixed seed of a render's hash options and
Morton-sorted photons, it would take the same place along the curve of a
cell batch after batch, a bias that does not average out.

Cost. The grid resolution is fixed, so the work per hit point grows with
its sphere: looking up every cell of its box, as a direct HJ10 does,
costs ~(2R/cell)^3 lookups. Here each column of cells along the short
axis is tested against the sphere, and an occupancy bitmap skips the
empty cells; that changes no result, since a
slot reached only through empty cells holds no photon in range. The kept
photons are copied per occupied cell in cell order, found by the cell's
rank among the bitmap's set bits, so neighbouring hit points read
neighbouring memory and the gather computes no hash. The work per hit
point is thus about pi (R/cell)^2 columns plus the occupied cells covered,
and it is never truncated: a hit point whose radius spans the whole box
visits every column (512 x 512 by default). `hash_statistics` reports the
cells covered per hit point (and photons lost), so benchmarks can show it.
Memory: the bitmap (4 MiB at 512 x 128 x 512) and its rank table (8 MiB),
plus about 70 bytes per occupied cell; the table's slots are never
allocated, so `table_size` only sets how often cells collide.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numba as nb
import numpy as np

from dosppm_core.kernels.anisotropic import frames_of, gather_f_framed, has_frame
from dosppm_core.kernels.materials import bsdf_rows, gather_tint
from dosppm_core.scene.model import ROUGH_DIELECTRIC
from dosppm_core.kernels.rng import mix64

RESOLUTION = (512, 128, 512)    # the paper's Table 1
MAX_TABLE_SIZE = 1 << 24        # default cap on slots
_MAX_BITMAP_WORDS = 1 << 28     # 2 GiB of occupancy bits
_RADIUS_SLACK = 1e-5            # relative: covers the float32 distance test
_SELECT_STREAM = np.uint64(3) << np.uint64(60)   # namespaced like rng.EYE_STREAM
_EMPTY = np.uint64(0xFFFFFFFFFFFFFFFF)
_LOW32 = np.uint64(0xFFFFFFFF)
_S32 = np.uint64(32)
_ONE, _ALL = np.uint64(1), np.uint64(0xFFFFFFFFFFFFFFFF)


# -- layout --------------------------------------------------------------------
@dataclass
class HashLayout:
    """The grid in internal axis order: internal axis 2 is the box's
    shortest (its cells are the bits of one bitmap column)."""
    lo: np.ndarray      # float64 (3,)
    cell: np.ndarray    # float64 (3,): cell size per internal axis
    dims: np.ndarray    # int64 (3,)
    axes: np.ndarray    # int64 (3,): the original axis of each internal axis
    table_size: int
    identity: bool      # table_size >= cell count: slot = cell id, no hashing
    slack: float        # absolute slack on radii and on the box, for rounding

    @property
    def cell_count(self) -> int:
        return int(np.prod(self.dims))

    def locate(self, ph_pos: np.ndarray, threads: int = 1):
        """(cell, slot) of each photon position, -1 outside the box: which
        photons compete for one kept photon (tests, diagnostics)."""
        pos = np.ascontiguousarray(ph_pos, np.float32)
        keys, cell_prio = _bin_photons(pos, pos.view(np.uint32), pos.view(np.uint32),
                                       np.uint64(0), self.lo, self.cell, self.dims, self.axes,
                                       self.slack, self.table_size, self.identity, int(threads))
        outside = keys == _EMPTY
        cells = (cell_prio >> _S32).astype(np.int64)
        slots = (keys >> _S32).astype(np.int64)
        cells[outside] = -1
        slots[outside] = -1
        return cells, slots


def hash_layout(hp_pos: np.ndarray, hp_radius: np.ndarray, resolution=RESOLUTION,
                table_size: int | None = None) -> HashLayout:
    """Grid over the hit points' box grown by the largest radius (§4.2):
    resolutions sorted ascending go to the axes sorted by extent."""
    res = sorted(int(r) for r in resolution)
    if len(res) != 3 or res[0] < 1:
        raise ValueError(f"resolution must be three positive ints, got {resolution!r}")
    rmax = float(hp_radius.max())
    lo = hp_pos.min(axis=0).astype(np.float64) - rmax
    hi = hp_pos.max(axis=0).astype(np.float64) + rmax
    ext = hi - lo
    ext = np.maximum(ext, 1e-9 * max(float(ext.max()), 1e-30))
    axes = np.argsort(ext, kind="stable")[::-1].astype(np.int64)   # longest first
    dims = np.array(res[::-1], np.int64)
    words = int(dims[0] * dims[1]) * ((int(dims[2]) + 63) // 64)
    if words > _MAX_BITMAP_WORDS:
        raise ValueError(f"resolution {tuple(resolution)} needs {words * 8 / 2**30:.1f} GiB "
                         "of occupancy bitmap; use a coarser grid")
    cells = int(np.prod(dims))
    size = min(cells, MAX_TABLE_SIZE) if table_size is None else int(table_size)
    if not 1 <= size < (1 << 32):
        raise ValueError(f"table_size must lie in [1, 2**32), got {table_size!r}")
    if cells >= (1 << 32):
        raise ValueError(f"resolution {tuple(resolution)} has 2**32 cells or more")
    identity = size >= cells
    # Slack for float64 rounding of the cell bounds, and for the float32
    # distance test, which may accept a photon a hair beyond the radius.
    scale = float(np.abs(np.concatenate([lo, hi])).max() + ext.max())
    slack = 1e-7 * scale + _RADIUS_SLACK * rmax
    return HashLayout(lo=lo[axes], cell=ext[axes] / dims, dims=dims, axes=axes,
                      table_size=size, identity=identity, slack=slack)


# -- scalar helpers (no array arguments: they are called in hot loops) ----------
@nb.njit(cache=True, nogil=True)
def _cell_index(p, lo, cell, d, slack):
    """Cell of coordinate p along one axis; points just outside the box
    (rounding) go to the edge cell, points beyond the slack to -1."""
    q = (p - lo) / cell
    if q >= 0.0 and q < d:
        return int(q)
    if q < 0.0 and p >= lo - slack:
        return 0
    if q >= d and p <= lo + d * cell + slack:
        return d - 1
    return -1


@nb.njit(cache=True, nogil=True)
def _cell_span(x, reach, lo, cell, d):
    """First and last cell along one axis that [x - reach, x + reach] touches."""
    a = math.floor((x - reach - lo) / cell)
    b = math.floor((x + reach - lo) / cell)
    return min(max(a, 0), d - 1), min(max(b, 0), d - 1)


@nb.njit(cache=True, nogil=True)
def _gap(x, i, lo, cell, d):
    """Distance from x to cell i along one axis; the edge cells reach to
    infinity, since they also hold the photons clamped into them."""
    if i > 0:
        left = lo + i * cell
        if x < left:
            return left - x
    if i < d - 1:
        right = lo + (i + 1) * cell
        if x > right:
            return x - right
    return 0.0


@nb.njit(cache=True, nogil=True)
def _slot(cell_id, table_size, identity):
    if identity:
        return cell_id
    return np.int64(mix64(np.uint64(cell_id)) % np.uint64(table_size))


@nb.njit(cache=True, nogil=True)
def _popcount(x):
    c = 0
    while x != 0:
        x &= x - _ONE
        c += 1
    return c


@nb.njit(cache=True, nogil=True)
def _word_mask(w, a, b):
    """Bits of word w that lie within cells [a, b] of a column."""
    lo_k = max(a - w * 64, 0)
    hi_k = min(b - w * 64, 63)
    return (_ALL >> np.uint64(63 - hi_k)) & (_ALL << np.uint64(lo_k))


# -- insertion -------------------------------------------------------------------
@nb.njit(cache=True, nogil=True, parallel=True)
def _bin_photons(ph_pos, pos_bits, dir_bits, seed_state, lo, cell, dims, axes, slack,
                 table_size, identity, threads):
    """Per photon: the sort key slot << 32 | index, and cell << 32 |
    priority, where the priority is a hash of (seed, the photon's position
    and direction bits); both all ones outside the box, so those sort last."""
    n = ph_pos.shape[0]
    keys = np.empty(n, np.uint64)
    cell_prio = np.empty(n, np.uint64)
    for t in nb.prange(threads):
        for j in range(n * t // threads, n * (t + 1) // threads):
            i0 = _cell_index(np.float64(ph_pos[j, axes[0]]), lo[0], cell[0], dims[0], slack)
            i1 = _cell_index(np.float64(ph_pos[j, axes[1]]), lo[1], cell[1], dims[1], slack)
            i2 = _cell_index(np.float64(ph_pos[j, axes[2]]), lo[2], cell[2], dims[2], slack)
            if i0 < 0 or i1 < 0 or i2 < 0:
                keys[j] = _EMPTY
                cell_prio[j] = _EMPTY
                continue
            c = (i0 * dims[1] + i1) * dims[2] + i2
            keys[j] = (np.uint64(_slot(c, table_size, identity)) << _S32) | np.uint64(j)
            p0, p1, p2 = pos_bits[j, 0], pos_bits[j, 1], pos_bits[j, 2]
            d0, d1, d2 = dir_bits[j, 0], dir_bits[j, 1], dir_bits[j, 2]
            h = mix64(seed_state ^ (np.uint64(p0) | (np.uint64(p1) << _S32)))
            h = mix64(h ^ (np.uint64(p2) | (np.uint64(d0) << _S32)))
            h = mix64(h ^ (np.uint64(d1) | (np.uint64(d2) << _S32)))
            cell_prio[j] = (np.uint64(c) << _S32) | (h >> _S32)
    return keys, cell_prio


@nb.njit(cache=True, nogil=True)
def _occupancy(cell_prio, columns, d2):
    """One bit per cell holding any photon (a column's cells contiguous),
    and per word the number of set bits before it: the rank of an
    occupied cell, which indexes the per-cell records."""
    words = (d2 + 63) // 64
    bitmap = np.zeros(columns * words, np.uint64)
    for j in range(cell_prio.shape[0]):
        if cell_prio[j] != _EMPTY:
            c = np.int64(cell_prio[j] >> _S32)
            col = c // d2
            i2 = c - col * d2
            bitmap[col * words + (i2 >> 6)] |= _ONE << np.uint64(i2 & 63)
    first = np.empty(bitmap.shape[0] + 1, np.int64)
    first[0] = 0
    for k in range(bitmap.shape[0]):
        first[k + 1] = first[k] + _popcount(bitmap[k])
    return bitmap, first


@nb.njit(cache=True, nogil=True)
def _run_bounds(keys, n_valid, threads):
    """Split the sorted keys into `threads` ranges that never cut a slot's run."""
    bounds = np.empty(threads + 1, np.int64)
    bounds[0] = 0
    for t in range(1, threads + 1):
        b = max(n_valid * t // threads, bounds[t - 1])
        while 0 < b < n_valid and (keys[b] >> _S32) == (keys[b - 1] >> _S32):
            b += 1
        bounds[t] = b
    return bounds


@nb.njit(cache=True, nogil=True, parallel=True)
def _run_starts(keys, bounds, threads):
    """Entry index at which each thread's range of sorted keys starts (its
    slots' runs are counted in parallel); the last is the entry count."""
    runs = np.zeros(threads + 1, np.int64)
    for t in nb.prange(threads):
        c = 0
        for i in range(bounds[t], bounds[t + 1]):
            if i == bounds[t] or (keys[i] >> _S32) != (keys[i - 1] >> _S32):
                c += 1
        runs[t + 1] = c
    for t in range(threads):
        runs[t + 1] += runs[t]
    return runs


@nb.njit(cache=True, nogil=True)
def _slot_run(keys, cell_prio, i, end):
    """The run of sorted keys of one slot from row i: where it ends, the
    photon of smallest priority (a tie, at odds of 2**-32 per pair, keeps
    the first by index) and whether photons of several cells share it."""
    s = keys[i] >> _S32
    best = np.int64(keys[i] & _LOW32)
    first_cell = cell_prio[best] >> _S32
    best_prio = cell_prio[best] & _LOW32
    multi = False
    j = i + 1
    while j < end and (keys[j] >> _S32) == s:
        p = np.int64(keys[j] & _LOW32)
        cp = cell_prio[p]
        multi = multi or (cp >> _S32) != first_cell
        if (cp & _LOW32) < best_prio:
            best, best_prio = p, cp & _LOW32
        j += 1
    return j, best, multi


@nb.njit(cache=True, nogil=True)
def _cell_rank(c, bitmap, first, words, d2):
    """Index of occupied cell c's record: its rank among the set bits."""
    col = c // d2
    i2 = c - col * d2
    word = col * words + (i2 >> 6)
    below = bitmap[word] & ~(_ALL << np.uint64(i2 & 63))
    return first[word] + _popcount(below)


@nb.njit(cache=True, nogil=True, parallel=True)
def _select_photons(keys, cell_prio, n_valid, bitmap, first, d2, photons, threads):
    """Keep one photon per slot: the one of smallest priority. `photons` is
    (position, incoming, flux). Returns per slot (entry, in slot
    order) its photon count and whether several cells share it, and per
    occupied cell (in cell order, found by its rank in the bitmap) its kept
    photon, photon count, shared entry (-1: none) and a copy of the photon,
    (3, cells, 3): position, incoming, flux.
    A cell belongs to one slot, so no two threads write one cell."""
    pos, inc, flux = photons
    words = (d2 + 63) // 64
    bounds = _run_bounds(keys, n_valid, threads)
    runs = _run_starts(keys, bounds, threads)
    e_count = np.empty(runs[threads], np.float64)
    e_multi = np.empty(runs[threads], np.bool_)
    cells = first[first.shape[0] - 1]
    # Filled, not empty: a cell left without its record must not read garbage.
    c_kept = np.full(cells, -1, np.int64)
    c_count = np.zeros(cells, np.float64)
    c_shared = np.full(cells, -1, np.int64)
    rows = np.zeros((3, cells, 3), np.float32)
    for t in nb.prange(threads):
        e, i, end = runs[t], bounds[t], bounds[t + 1]
        while i < end:
            j, best, multi = _slot_run(keys, cell_prio, i, end)
            e_count[e], e_multi[e] = j - i, multi
            # The records of the slot's cells (all its photons' cells if shared).
            for k in range(i, j if multi else i + 1):
                c = np.int64(cell_prio[np.int64(keys[k] & _LOW32)] >> _S32)
                rank = _cell_rank(c, bitmap, first, words, d2)
                c_kept[rank], c_count[rank] = best, j - i
                c_shared[rank] = e if multi else -1
                for a in range(3):
                    rows[0, rank, a] = pos[best, a]
                    rows[1, rank, a] = inc[best, a]
                    rows[2, rank, a] = flux[best, a]
            e += 1
            i = j
    return e_count, e_multi, c_kept, c_count, c_shared, rows


# -- the gather --------------------------------------------------------------------
@nb.njit(cache=True, nogil=True, parallel=True)
def _gather(hp, frames, hp_radius, grid, cells, entries, materials, threads):
    """M and Phi per hit point. `hp` is (position, normal, outgoing, eye
    weight, material), `frames` their lobes' (`anisotropic.frames_of`: None
    compiles the gather without them), `grid` (lo, cell, dims, axes, slack,
    bitmap, first) in internal axis order, `cells` the occupied cells'
    records (position, incoming, flux, count, shared entry), `materials`
    (kind, gather_tint, roughness, bsdf_rows). Hit points are split in `threads` ranges; each
    thread writes only its own hit points. `stamp` remembers, per thread,
    the last hit point that took each entry whose slot several cells
    share: only those can be reached twice."""
    nhp = hp[0].shape[0]
    m = np.zeros(nhp)
    phi = np.zeros((nhp, 3))
    stamp = np.zeros((threads, entries), np.int64)
    for t in nb.prange(threads):
        _gather_range(nhp * t // threads, nhp * (t + 1) // threads, hp, frames, hp_radius, grid, cells,
                      materials, stamp[t], m, phi)
    return m, phi


@nb.njit(cache=True, nogil=True)
def _gather_range(first_hp, end_hp, hp, frames, hp_radius, grid, cells, materials, stamp, m, phi):
    """M and Phi of hit points [first_hp, end_hp), one thread's range."""
    hp_n, hp_mat = hp[1], hp[4]
    mat_kind, mat_refl, mat_rough, mat_bsdf = materials
    for h in range(first_hp, end_hp):
        mat = hp_mat[h]
        shading = (hp_n[h, 0], hp_n[h, 1], hp_n[h, 2], mat_kind[mat], np.float64(mat_rough[mat]),
                   mat_refl[mat, 0], mat_refl[mat, 1], mat_refl[mat, 2])
        framed = has_frame(mat_kind[mat], mat_bsdf, mat, frames, h)     # asked once, not per photon
        m[h], phi[h, 0], phi[h, 1], phi[h, 2] = _gather_hit_point(
            h, hp_radius[h], hp, frames, shading, (mat_bsdf, mat, framed), grid, cells, stamp)


@nb.njit(cache=True, nogil=True, inline="always")
def _gather_hit_point(h, r, hp, frames, shading, material, grid, cells, stamp):
    """(M, Phi) of hit point h of radius r: the columns of cells its sphere overlaps, in
    each the occupied cells (found in the bitmap, their records by rank), and their kept
    photons' distance and BRDF tests. The loops stay in one function: a call taking arrays,
    per word or photon, would reference-count each of them (numba), at twice the time."""
    hp_pos, _hp_n, hp_out, hp_weight, _hp_mat = hp
    lo, cell, dims, axes, slack, bitmap, first = grid
    c_pos, c_in, c_flux, c_count, c_shared = cells
    (n0, n1, n2, kind, rough, refl0, refl1, refl2), (bsdf, mat, framed) = shading, material
    words = (dims[2] + 63) // 64
    x, y, z = np.float64(hp_pos[h, axes[0]]), np.float64(hp_pos[h, axes[1]]), np.float64(hp_pos[h, axes[2]])
    reach = r * (1.0 + _RADIUS_SLACK) + slack
    acc_m, acc0, acc1, acc2 = 0.0, 0.0, 0.0, 0.0
    a0, b0 = _cell_span(x, reach, lo[0], cell[0], dims[0])
    a1, b1 = _cell_span(y, reach, lo[1], cell[1], dims[1])
    for i0 in range(a0, b0 + 1):
        g0 = _gap(x, i0, lo[0], cell[0], dims[0])
        rest0 = reach * reach - g0 * g0
        if rest0 < 0.0:
            continue
        for i1 in range(a1, b1 + 1):
            g1 = _gap(y, i1, lo[1], cell[1], dims[1])
            rest = rest0 - g1 * g1
            if rest < 0.0:
                continue
            a2, b2 = _cell_span(z, math.sqrt(rest), lo[2], cell[2], dims[2])
            col = (i0 * dims[1] + i1) * words
            for w in range(a2 >> 6, (b2 >> 6) + 1):
                word = bitmap[col + w]
                bits = word & _word_mask(w, a2, b2)
                if bits == 0:
                    continue
                # Rank of the first cell in range = bits set before it.
                start = np.uint64(max(a2 - w * 64, 0))
                k = first[col + w] + _popcount(word & ~(_ALL << start)) - 1
                while bits != 0:
                    bits &= bits - _ONE
                    k += 1
                    e = c_shared[k]
                    if e >= 0:
                        if stamp[e] == h + 1:
                            continue
                        stamp[e] = h + 1
                    d0 = c_pos[k, 0] - hp_pos[h, 0]
                    d1 = c_pos[k, 1] - hp_pos[h, 1]
                    d2 = c_pos[k, 2] - hp_pos[h, 2]
                    if (d0 * d0 + d1 * d1 + d2 * d2 > r * r
                            or (n0 * c_in[k, 0] + n1 * c_in[k, 1] + n2 * c_in[k, 2] <= 0.0
                                and kind != ROUGH_DIELECTRIC)):
                        continue    # outside the sphere, or from behind the surface (grid.py)
                    f0, f1, f2 = gather_f_framed(framed, kind, rough, bsdf, mat, frames, h, n0, n1, n2,
                                                 hp_out[h, 0], hp_out[h, 1], hp_out[h, 2],
                                                 c_in[k, 0], c_in[k, 1], c_in[k, 2])
                    cnt = c_count[k]
                    acc_m += cnt
                    if f0 + f1 + f2 > 0.0:
                        acc0 += cnt * (f0 * refl0 * hp_weight[h, 0] * c_flux[k, 0])
                        acc1 += cnt * (f1 * refl1 * hp_weight[h, 1] * c_flux[k, 1])
                        acc2 += cnt * (f2 * refl2 * hp_weight[h, 2] * c_flux[k, 2])
    return acc_m, acc0, acc1, acc2


@nb.njit(cache=True, nogil=True)
def _cells_covered(hp_pos, hp_radius, lo, cell, dims, axes, slack, bitmap):
    """Per hit point: cells its sphere overlaps (what HJ10 looks up) and
    occupied cells among them (what `_gather` looks at). Serial: it is a
    diagnostic, and a parallel kernel costs seconds more to compile."""
    nhp = hp_pos.shape[0]
    covered = np.zeros(nhp, np.int64)
    occupied = np.zeros(nhp, np.int64)
    words = (dims[2] + 63) // 64
    for h in range(nhp):
        x = np.float64(hp_pos[h, axes[0]])
        y = np.float64(hp_pos[h, axes[1]])
        z = np.float64(hp_pos[h, axes[2]])
        reach = hp_radius[h] * (1.0 + _RADIUS_SLACK) + slack
        a0, b0 = _cell_span(x, reach, lo[0], cell[0], dims[0])
        a1, b1 = _cell_span(y, reach, lo[1], cell[1], dims[1])
        for i0 in range(a0, b0 + 1):
            g0 = _gap(x, i0, lo[0], cell[0], dims[0])
            for i1 in range(a1, b1 + 1):
                g1 = _gap(y, i1, lo[1], cell[1], dims[1])
                rest = reach * reach - g0 * g0 - g1 * g1
                if rest < 0.0:
                    continue
                a2, b2 = _cell_span(z, math.sqrt(rest), lo[2], cell[2], dims[2])
                covered[h] += b2 - a2 + 1
                col = (i0 * dims[1] + i1) * words
                for w in range(a2 >> 6, (b2 >> 6) + 1):
                    occupied[h] += _popcount(bitmap[col + w] & _word_mask(w, a2, b2))
    return covered, occupied


# -- the table as an object --------------------------------------------------------
@dataclass
class PhotonHash:
    """The filled stochastic hash. Entries: one per occupied slot, in slot
    order. Cell records: one per occupied cell, in cell order (the order
    of the bitmap's set bits), holding a copy of its slot's kept photon."""
    layout: HashLayout
    bitmap: np.ndarray          # uint64: occupied cells
    first: np.ndarray           # int64: set bits before each bitmap word
    count: np.ndarray           # float64 (E,): photons that fell into the slot
    multi: np.ndarray           # bool (E,): the slot holds photons of several cells
    cell_photon: np.ndarray     # int64 (C,): input index of each occupied cell's kept photon
    cell_count: np.ndarray      # float64 (C,): its slot's photon count
    cell_shared: np.ndarray     # int64 (C,): its entry if several cells share it, else -1
    position: np.ndarray        # float32 (C, 3), and the kept photons' other fields
    incoming: np.ndarray
    flux: np.ndarray
    photons: int                # photons offered
    photons_binned: int         # of those, inside the grid's box

    @property
    def photons_discarded(self) -> int:
        """Photons lost to collisions: binned but not kept."""
        return self.photons_binned - len(self.count)

    @property
    def discarded_fraction(self) -> float:
        return self.photons_discarded / self.photons_binned if self.photons_binned else 0.0

    def gather(self, hp, hp_radius: np.ndarray, materials, threads: int):
        """(M, Phi) per hit point: M the expected photon count, Phi the
        expected BRDF-weighted flux times the eye path weight."""
        L = self.layout
        return _gather((hp.position, hp.normal, hp.outgoing, hp.weight, hp.material), frames_of(hp),
                       np.asarray(hp_radius, np.float64),
                       (L.lo, L.cell, L.dims, L.axes, L.slack, self.bitmap, self.first),
                       (self.position, self.incoming, self.flux, self.cell_count,
                        self.cell_shared),
                       len(self.count), (materials.kind, gather_tint(materials),
                                         materials.roughness, bsdf_rows(materials)), int(threads))

    def cells_covered(self, hp_pos: np.ndarray, hp_radius: np.ndarray):
        """(cells overlapped, occupied cells overlapped) per hit point."""
        L = self.layout
        return _cells_covered(hp_pos, np.asarray(hp_radius, np.float64), L.lo, L.cell, L.dims,
                              L.axes, L.slack, self.bitmap)


def build_photon_hash(ph, hp_pos: np.ndarray, hp_radius: np.ndarray, threads: int,
                      resolution=RESOLUTION, table_size: int | None = None,
                      seed: int = 0) -> PhotonHash:
    """Bin the deposits `ph` into the hash laid out over the hit points and
    keep one photon per slot."""
    if threads < 1:
        raise ValueError(f"threads must be >= 1, got {threads}")
    if len(ph.position) >= (1 << 32):
        raise ValueError("at most 2**32 - 1 photons per batch")
    L = hash_layout(hp_pos, np.asarray(hp_radius, np.float64), resolution, table_size)
    threads = int(threads)
    pos = np.ascontiguousarray(ph.position, np.float32)
    inc = np.ascontiguousarray(ph.incoming, np.float32)
    seed_state = np.uint64(mix64(np.uint64(seed & 0xFFFFFFFFFFFFFFFF) ^ _SELECT_STREAM))
    # Bin, mark the occupied cells, sort by slot, keep one photon per slot.
    keys, cell_prio = _bin_photons(pos, pos.view(np.uint32), inc.view(np.uint32), seed_state,
                                   L.lo, L.cell, L.dims, L.axes, L.slack, L.table_size,
                                   L.identity, threads)
    bitmap, first = _occupancy(cell_prio, int(L.dims[0] * L.dims[1]), int(L.dims[2]))
    keys.sort()
    n_valid = int(np.searchsorted(keys, _EMPTY))
    photons = (pos, inc, np.ascontiguousarray(ph.flux, np.float32))
    count, multi, c_kept, c_count, c_shared, rows = _select_photons(
        keys, cell_prio, n_valid, bitmap, first, int(L.dims[2]), photons, threads)
    return PhotonHash(layout=L, bitmap=bitmap, first=first, count=count, multi=multi,
                      cell_photon=c_kept, cell_count=c_count, cell_shared=c_shared,
                      position=rows[0], incoming=rows[1], flux=rows[2],
                      photons=len(pos), photons_binned=n_valid)


def gather_hash(ph, hp, hp_radius, materials, threads: int, resolution=RESOLUTION,
                table_size: int | None = None, seed: int = 0):
    """Stochastic gather of photon deposits `ph` at hit points `hp` (HJ10).
    Returns (M, Phi) per hit point, unbiased estimates of the grid gather's
    (M is the expected photon count: a kept photon in range adds its
    slot's count).

    resolution: grid cells per axis, the smallest to the box's shortest
    axis. table_size: hash slots (default min(cells, 2**24)); at or above
    the cell count each cell gets its own slot. seed: drives which photon a
    slot keeps; a fixed seed is fine across batches (see the module notes)."""
    if len(hp) == 0 or len(ph.position) == 0:   # len(ph) of a GatherPhotons tuple is 3
        return np.zeros(len(hp)), np.zeros((len(hp), 3))
    table = build_photon_hash(ph, hp.position, hp_radius, threads, resolution, table_size, seed)
    return table.gather(hp, hp_radius, materials, threads)


def hash_statistics(ph, hp, hp_radius, threads: int = 2, resolution=RESOLUTION,
                    table_size: int | None = None, seed: int = 0) -> dict:
    """Diagnostics of the hash for one batch (for benchmarks): photons lost
    to collisions and the cells a hit point covers (the method's cost)."""
    table = build_photon_hash(ph, hp.position, hp_radius, threads, resolution, table_size, seed)
    covered, occupied = table.cells_covered(hp.position, hp_radius)
    L = table.layout
    dims = np.empty(3, np.int64)
    dims[L.axes] = L.dims
    return {
        "photons": table.photons,
        "photons_binned": table.photons_binned,
        "slots_used": len(table.count),
        "photons_discarded": table.photons_discarded,
        "discarded_fraction": table.discarded_fraction,
        "multi_cell_slots": int(table.multi.sum()),
        "occupied_cells": len(table.cell_count),
        "table_size": L.table_size,
        "cells": L.cell_count,
        "dims_xyz": tuple(int(d) for d in dims),
        "cells_per_hit_point_mean": float(covered.mean()) if len(covered) else 0.0,
        "cells_per_hit_point_max": int(covered.max()) if len(covered) else 0,
        "occupied_cells_per_hit_point_mean": float(occupied.mean()) if len(occupied) else 0.0,
        "occupied_cells_per_hit_point_max": int(occupied.max()) if len(occupied) else 0,
    }
