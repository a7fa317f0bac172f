"""The exact `grid` gather (pbrt-v4's SPPM layout, the "reverse"
organisation of the Photon Pipeline paper): hit points are inserted into
every cell of a hashed uniform grid that their radius overlaps, and each
photon visits only its own cell. No photon is lost: every hit point within
a photon's radius is registered in the photon's cell.

Entries carry their cell key, so two cells hashing to one slot can neither
lend each other hit points nor count a hit point twice.
"""
import math

import numba as nb
import numpy as np

from .kernels.bsdf import eval_bsdf

NORMAL_COS = 0.5   # photon and hit point must lie on similarly facing surfaces
_P1, _P2, _P3 = 73856093, 19349663, 83492791


@nb.njit(cache=True, error_model="numpy")
def cell_key(ix, iy, iz):
    return (np.int64(ix) << 42) | (np.int64(iy) << 21) | np.int64(iz)


@nb.njit(cache=True, error_model="numpy")
def slot_of(ix, iy, iz, mask):
    return ((ix * _P1) ^ (iy * _P2) ^ (iz * _P3)) & mask


@nb.njit(cache=True, error_model="numpy")
def build_grid(hp_pos, hp_radius, lo, cell, dims):
    """Returns (slot_start, entry_hp, entry_key, mask): a CSR table from
    hash slot to the hit points registered in the cells hashing there."""
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
    size = 1
    while size < 2 * total:
        size *= 2
    mask = size - 1
    counts = np.zeros(size + 1, np.int64)
    for i in range(n):
        for ix in range(lo_c[i, 0], hi_c[i, 0] + 1):
            for iy in range(lo_c[i, 1], hi_c[i, 1] + 1):
                for iz in range(lo_c[i, 2], hi_c[i, 2] + 1):
                    counts[slot_of(ix, iy, iz, mask) + 1] += 1
    start = np.cumsum(counts)
    fill = start[:-1].copy()
    entry_hp = np.empty(total, np.int32)
    entry_key = np.empty(total, np.int64)
    for i in range(n):
        for ix in range(lo_c[i, 0], hi_c[i, 0] + 1):
            for iy in range(lo_c[i, 1], hi_c[i, 1] + 1):
                for iz in range(lo_c[i, 2], hi_c[i, 2] + 1):
                    s = slot_of(ix, iy, iz, mask)
                    entry_hp[fill[s]] = i
                    entry_key[fill[s]] = cell_key(ix, iy, iz)
                    fill[s] += 1
    return start, entry_hp, entry_key, mask


@nb.njit(cache=True, parallel=True, error_model="numpy")
def gather_photons(ph_pos, ph_in, ph_n, ph_flux, start, entry_hp, entry_key, mask,
                   lo, cell, dims, hp_pos, hp_n, hp_out, hp_weight, hp_mat, hp_radius,
                   mat_kind, mat_refl, mat_rough, threads):
    """Accumulate, per hit point, the photon count M and the BRDF-weighted
    flux Phi (eq. 3, times the eye path weight). numba has no atomics on
    the CPU, so each thread owns an accumulator over a contiguous range of
    the (spatially sorted) photons; they are summed at the end."""
    nhp = hp_pos.shape[0]
    n = ph_pos.shape[0]
    acc_m = np.zeros((threads, nhp))
    acc_phi = np.zeros((threads, nhp, 3))
    for t in nb.prange(threads):
        for j in range(n * t // threads, n * (t + 1) // threads):
            px, py, pz = ph_pos[j, 0], ph_pos[j, 1], ph_pos[j, 2]
            ix = int(math.floor((px - lo[0]) / cell))
            iy = int(math.floor((py - lo[1]) / cell))
            iz = int(math.floor((pz - lo[2]) / cell))
            if ix < 0 or iy < 0 or iz < 0 or ix >= dims[0] or iy >= dims[1] or iz >= dims[2]:
                continue
            key = cell_key(ix, iy, iz)
            s = slot_of(ix, iy, iz, mask)
            # The hot loop stays free of calls taking arrays: numba would
            # reference-count every array argument of every call.
            for e in range(start[s], start[s + 1]):
                if entry_key[e] != key:
                    continue
                h = entry_hp[e]
                d0, d1, d2 = px - hp_pos[h, 0], py - hp_pos[h, 1], pz - hp_pos[h, 2]
                r = hp_radius[h]
                if d0 * d0 + d1 * d1 + d2 * d2 > r * r:
                    continue
                n0, n1, n2 = hp_n[h, 0], hp_n[h, 1], hp_n[h, 2]
                if n0 * ph_n[j, 0] + n1 * ph_n[j, 1] + n2 * ph_n[j, 2] < NORMAL_COS:
                    continue
                mat = hp_mat[h]
                f = eval_bsdf(mat_kind[mat], np.float64(mat_rough[mat]), n0, n1, n2,
                              hp_out[h, 0], hp_out[h, 1], hp_out[h, 2],
                              ph_in[j, 0], ph_in[j, 1], ph_in[j, 2])
                acc_m[t, h] += 1.0
                if f > 0.0:
                    for k in range(3):
                        acc_phi[t, h, k] += f * mat_refl[mat, k] * hp_weight[h, k] * ph_flux[j, k]
    m = np.zeros(nhp)
    phi = np.zeros((nhp, 3))
    for t in range(threads):
        m += acc_m[t]
        phi += acc_phi[t]
    return m, phi


def grid_layout(hp_pos: np.ndarray, hp_radius: np.ndarray):
    """Grid origin, cell size and dims: cells of twice the median radius
    over the hit points' box grown by the largest radius, so a typical hit
    point lands in at most 8 cells."""
    rmax = float(hp_radius.max())
    lo = hp_pos.min(axis=0).astype(np.float64) - rmax
    hi = hp_pos.max(axis=0).astype(np.float64) + rmax
    cell = 2.0 * float(np.median(hp_radius))
    cell = max(cell, float((hi - lo).max()) / (1 << 20))   # keys hold 21 bits per axis
    dims = np.maximum(np.ceil((hi - lo) / cell).astype(np.int64), 1)
    return lo, cell, dims


def gather_grid(ph, hp, hp_radius, materials, threads: int):
    """Exact gather of photon deposits `ph` at hit points `hp`. Returns
    (M, Phi) per hit point."""
    if len(hp) == 0 or len(ph) == 0:
        return np.zeros(len(hp)), np.zeros((len(hp), 3))
    lo, cell, dims = grid_layout(hp.position, hp_radius)
    start, entry_hp, entry_key, mask = build_grid(hp.position, hp_radius, lo, cell, dims)
    return gather_photons(ph.position, ph.incoming, ph.normal, ph.flux, start, entry_hp,
                          entry_key, mask, lo, cell, dims, hp.position, hp.normal, hp.outgoing,
                          hp.weight, hp.material, hp_radius, materials.kind,
                          materials.reflectance, materials.roughness, threads)
