"""One bounce of a batch of photon or eye paths, after intersection.

Each kernel reads the closest hits of a batch and writes, per ray, what
happened: a deposit or a hit point, the continuing ray, and why the path
ended (codes in `dosppm_core.jobs`). Compaction is left to the caller so
that the same step serves a whole scene or one chunk.
"""
import math

import numba as nb
import numpy as np

from dosppm_core.jobs import ABSORBED, CONTINUES, ESCAPED, MAX_DEPTH, STORED
from dosppm_core.kernels.bsdf import is_specular, sample_bsdf
from dosppm_core.kernels.rng import next_float

# `prim` of a ray whose hit lies in another chunk (it left through a
# portal): the bounce kernels skip its row, so a chunk's batch need not be
# split and copied before each bounce; only the leaving rows are moved.
ELSEWHERE = -2
SKIPPED = -1    # its end code: counted nowhere, output nowhere


@nb.njit(cache=True, error_model="numpy")
def surface(v0, v1, v2, u, v):
    """Hit position (from barycentrics, float64: more exact than o + t d)
    and the unit CCW geometric normal, from the triangle's vertex rows."""
    w = 1.0 - u - v
    p0 = w * np.float64(v0[0]) + u * np.float64(v1[0]) + v * np.float64(v2[0])
    p1 = w * np.float64(v0[1]) + u * np.float64(v1[1]) + v * np.float64(v2[1])
    p2 = w * np.float64(v0[2]) + u * np.float64(v1[2]) + v * np.float64(v2[2])
    a0, a1, a2 = np.float64(v1[0]) - v0[0], np.float64(v1[1]) - v0[1], np.float64(v1[2]) - v0[2]
    b0, b1, b2 = np.float64(v2[0]) - v0[0], np.float64(v2[1]) - v0[1], np.float64(v2[2]) - v0[2]
    nx = a1 * b2 - a2 * b1
    ny = a2 * b0 - a0 * b2
    nz = a0 * b1 - a1 * b0
    nl = math.sqrt(nx * nx + ny * ny + nz * nz)
    return p0, p1, p2, nx / nl, ny / nl, nz / nl


@nb.njit(cache=True, error_model="numpy")
def offset_origin(p0, p1, p2, n0, n1, n2, w0, w1, w2, eps_rel, eps_abs):
    """Spawn point off the surface on the side of direction w. Embree's
    tnear is 0, so without this a ray re-hits its own triangle; the offset
    is relative to |p| so scenes far from the origin still clear float32."""
    eps = eps_rel * max(abs(p0), abs(p1), abs(p2)) + eps_abs
    if n0 * w0 + n1 * w1 + n2 * w2 < 0.0:
        eps = -eps
    return p0 + eps * n0, p1 + eps * n1, p2 + eps * n2


@nb.njit(cache=True, error_model="numpy")
def _indices(mask):
    """Positions where mask is true (sequential: cheap next to the bounce)."""
    out = np.empty(mask.shape[0], np.int64)
    c = 0
    for i in range(mask.shape[0]):
        if mask[i]:
            out[c] = i
            c += 1
    return out[:c]


@nb.njit(cache=True, parallel=True, error_model="numpy")
def _rows(a, idx):
    out = np.empty((idx.shape[0], a.shape[1]), a.dtype)
    for j in nb.prange(idx.shape[0]):
        for k in range(a.shape[1]):
            out[j, k] = a[idx[j], k]
    return out


@nb.njit(cache=True, error_model="numpy")
def _ends(end):
    counts = np.zeros(5, np.int64)
    for i in range(end.shape[0]):
        if end[i] >= 0:                 # SKIPPED rows are not this step's
            counts[end[i]] += 1
    return counts


@nb.njit(cache=True, error_model="numpy")
def _block_starts(counts, col):
    """Exclusive prefix sum of one column of per-block counts."""
    out = np.empty(counts.shape[0] + 1, np.int64)
    out[0] = 0
    for b in range(counts.shape[0]):
        out[b + 1] = out[b] + counts[b, col]
    return out


@nb.njit(cache=True, parallel=True, error_model="numpy")
def scatter_photons(origin, direction, flux, depth, states, job, pixel, prim, u, v,
                    vertices, triangles, tri_material, mat_kind, mat_refl, mat_ior,
                    mat_rough, mat_two_sided, cull_lo, cull_hi, max_depth,
                    eps_rel, eps_abs):
    """Deposit photons at non-specular hits (if inside the cull box) and
    scatter them with Russian roulette. Returns (end counts, culled count,
    deposits (position, incoming, normal, flux, job), continuing paths
    (origin, direction, flux, rng state, depth, job, pixel)).

    Compaction is done here, in blocks: each block of rows writes its
    deposits and survivors densely from its own start, then one parallel
    pass packs the blocks. A mask-then-gather compaction (or numpy's
    boolean indexing) cost as much as the bounce itself."""
    n = origin.shape[0]
    nblk = max(1, min(64, n // 2048))   # enough blocks to balance threads
    end = np.empty(n, np.int8)
    culled = np.zeros(n, np.bool_)
    dep_pos = np.empty((n, 3), np.float32)
    dep_in = np.empty((n, 3), np.float32)
    dep_n = np.empty((n, 3), np.float32)
    dep_f = np.empty((n, 3), np.float32)
    dep_job = np.empty(n, np.int64)
    new_o = np.empty((n, 3), np.float32)
    new_d = np.empty((n, 3), np.float32)
    new_f = np.empty((n, 3), np.float32)
    new_st = np.empty(n, np.uint64)
    new_depth = np.empty(n, np.int32)
    new_job = np.empty(n, np.int64)
    new_pix = np.empty(n, np.int32)
    counts = np.zeros((nblk, 2), np.int64)
    for b in nb.prange(nblk):
        a = b * n // nblk
        e = (b + 1) * n // nblk
        dc = a
        gc = a
        for i in range(a, e):
            tri = prim[i]
            if tri < 0:
                end[i] = ESCAPED if tri != ELSEWHERE else SKIPPED
                continue
            t0, t1, t2 = triangles[tri, 0], triangles[tri, 1], triangles[tri, 2]
            p0, p1, p2, n0, n1, n2 = surface(vertices[t0], vertices[t1], vertices[t2],
                                             np.float64(u[i]), np.float64(v[i]))
            w0, w1, w2 = -direction[i, 0], -direction[i, 1], -direction[i, 2]
            m = tri_material[tri]
            kind = mat_kind[m]
            front = n0 * w0 + n1 * w1 + n2 * w2 > 0.0
            if not is_specular(kind):
                if not front and not mat_two_sided[m]:
                    end[i] = ABSORBED
                    continue
                if (p0 < cull_lo[0] or p0 > cull_hi[0] or p1 < cull_lo[1] or p1 > cull_hi[1]
                        or p2 < cull_lo[2] or p2 > cull_hi[2]):
                    culled[i] = True
                else:
                    s = 1.0 if front else -1.0
                    dep_pos[dc, 0], dep_pos[dc, 1], dep_pos[dc, 2] = p0, p1, p2
                    dep_in[dc, 0], dep_in[dc, 1], dep_in[dc, 2] = w0, w1, w2
                    dep_n[dc, 0], dep_n[dc, 1], dep_n[dc, 2] = s * n0, s * n1, s * n2
                    dep_f[dc, 0], dep_f[dc, 1], dep_f[dc, 2] = flux[i, 0], flux[i, 1], flux[i, 2]
                    dep_job[dc] = job[i]
                    dc += 1
            if depth[i] + 1 >= max_depth:
                end[i] = MAX_DEPTH
                continue
            st = states[i]
            st, u1 = next_float(st)
            st, u2 = next_float(st)
            st, u3 = next_float(st)
            st, ur = next_float(st)
            ok, d0, d1, d2, scale, spec = sample_bsdf(kind, mat_two_sided[m], np.float64(mat_ior[m]),
                                                      np.float64(mat_rough[m]), n0, n1, n2, w0, w1, w2,
                                                      u1, u2, u3, False)
            if not ok:
                end[i] = ABSORBED
                continue
            old_max = max(flux[i, 0], flux[i, 1], flux[i, 2])
            nf0 = flux[i, 0] * mat_refl[m, 0] * scale
            nf1 = flux[i, 1] * mat_refl[m, 1] * scale
            nf2 = flux[i, 2] * mat_refl[m, 2] * scale
            q = max(0.0, 1.0 - max(nf0, nf1, nf2) / old_max) if old_max > 0 else 1.0
            if ur < q:
                end[i] = ABSORBED
                continue
            keep = 1.0 / (1.0 - q)
            new_f[gc, 0], new_f[gc, 1], new_f[gc, 2] = nf0 * keep, nf1 * keep, nf2 * keep
            dl = math.sqrt(d0 * d0 + d1 * d1 + d2 * d2)
            new_d[gc, 0], new_d[gc, 1], new_d[gc, 2] = d0 / dl, d1 / dl, d2 / dl
            new_o[gc, 0], new_o[gc, 1], new_o[gc, 2] = offset_origin(
                p0, p1, p2, n0, n1, n2, d0, d1, d2, eps_rel, eps_abs)
            new_st[gc] = st
            new_depth[gc] = depth[i] + 1
            new_job[gc] = job[i]
            new_pix[gc] = pixel[i]
            gc += 1
            end[i] = CONTINUES
        counts[b, 0] = dc - a
        counts[b, 1] = gc - a
    ds = _block_starts(counts, 0)
    gs = _block_starts(counts, 1)
    o_pos = np.empty((ds[nblk], 3), np.float32)
    o_in = np.empty((ds[nblk], 3), np.float32)
    o_n = np.empty((ds[nblk], 3), np.float32)
    o_f = np.empty((ds[nblk], 3), np.float32)
    o_job = np.empty(ds[nblk], np.int64)
    c_o = np.empty((gs[nblk], 3), np.float32)
    c_d = np.empty((gs[nblk], 3), np.float32)
    c_f = np.empty((gs[nblk], 3), np.float32)
    c_st = np.empty(gs[nblk], np.uint64)
    c_depth = np.empty(gs[nblk], np.int32)
    c_job = np.empty(gs[nblk], np.int64)
    c_pix = np.empty(gs[nblk], np.int32)
    for b in nb.prange(nblk):
        a = b * n // nblk
        for j in range(counts[b, 0]):
            o = ds[b] + j
            for k in range(3):
                o_pos[o, k] = dep_pos[a + j, k]
                o_in[o, k] = dep_in[a + j, k]
                o_n[o, k] = dep_n[a + j, k]
                o_f[o, k] = dep_f[a + j, k]
            o_job[o] = dep_job[a + j]
        for j in range(counts[b, 1]):
            o = gs[b] + j
            for k in range(3):
                c_o[o, k] = new_o[a + j, k]
                c_d[o, k] = new_d[a + j, k]
                c_f[o, k] = new_f[a + j, k]
            c_st[o] = new_st[a + j]
            c_depth[o] = new_depth[a + j]
            c_job[o] = new_job[a + j]
            c_pix[o] = new_pix[a + j]
    return (_ends(end), int(culled.sum()), (o_pos, o_in, o_n, o_f, o_job),
            (c_o, c_d, c_f, c_st, c_depth, c_job, c_pix))


@nb.njit(cache=True, parallel=True, error_model="numpy")
def advance_eye_paths(direction, weight, depth, states, prim, u, v,
                      vertices, triangles, tri_material, mat_kind, mat_refl, mat_emit,
                      mat_ior, mat_rough, mat_two_sided, max_depth, eps_rel, eps_abs):
    """Record emission seen along eye paths, store a hit point at the first
    non-specular surface, and continue through mirrors and glass. Returns
    (end counts, emission (index into the batch, rgb), hit points (index,
    position, normal), continuing paths (index, origin, direction, weight,
    rng state)); a hit point's outgoing direction is -direction and its
    material tri_material[prim]."""
    n = direction.shape[0]
    end = np.empty(n, np.int8)
    emitted = np.zeros((n, 3), np.float32)
    hp_pos = np.empty((n, 3), np.float32)
    hp_n = np.empty((n, 3), np.float32)
    new_o = np.empty((n, 3), np.float32)
    new_d = np.empty((n, 3), np.float32)
    new_w = np.empty((n, 3), np.float32)
    out_states = states.copy()
    for i in nb.prange(n):
        tri = prim[i]
        if tri < 0:
            end[i] = ESCAPED if tri != ELSEWHERE else SKIPPED
            continue
        t0, t1, t2 = triangles[tri, 0], triangles[tri, 1], triangles[tri, 2]
        p0, p1, p2, n0, n1, n2 = surface(vertices[t0], vertices[t1], vertices[t2],
                                         np.float64(u[i]), np.float64(v[i]))
        w0, w1, w2 = -direction[i, 0], -direction[i, 1], -direction[i, 2]
        m = tri_material[tri]
        kind = mat_kind[m]
        front = n0 * w0 + n1 * w1 + n2 * w2 > 0.0
        if front:  # one-sided emitters, as in Mitsuba
            for k in range(3):
                emitted[i, k] = weight[i, k] * mat_emit[m, k]
        if not is_specular(kind):
            if not front and not mat_two_sided[m]:
                end[i] = ABSORBED
                continue
            s = 1.0 if front else -1.0
            hp_pos[i, 0], hp_pos[i, 1], hp_pos[i, 2] = p0, p1, p2
            hp_n[i, 0], hp_n[i, 1], hp_n[i, 2] = s * n0, s * n1, s * n2
            end[i] = STORED
            continue
        if depth[i] + 1 >= max_depth:
            end[i] = MAX_DEPTH
            continue
        st = states[i]
        st, u1 = next_float(st)
        out_states[i] = st
        ok, d0, d1, d2, scale, spec = sample_bsdf(kind, mat_two_sided[m], np.float64(mat_ior[m]),
                                                  np.float64(mat_rough[m]), n0, n1, n2, w0, w1, w2,
                                                  u1, 0.5, 0.5, True)
        if not ok:
            end[i] = ABSORBED
            continue
        for k in range(3):
            new_w[i, k] = weight[i, k] * mat_refl[m, k] * scale
        dl = math.sqrt(d0 * d0 + d1 * d1 + d2 * d2)
        new_d[i, 0], new_d[i, 1], new_d[i, 2] = d0 / dl, d1 / dl, d2 / dl
        new_o[i, 0], new_o[i, 1], new_o[i, 2] = offset_origin(
            p0, p1, p2, n0, n1, n2, d0, d1, d2, eps_rel, eps_abs)
        end[i] = CONTINUES
    lit = _indices(emitted.sum(axis=1) > 0.0)
    h = _indices(end == STORED)
    g = _indices(end == CONTINUES)
    return (_ends(end), (lit, _rows(emitted, lit)), (h, _rows(hp_pos, h), _rows(hp_n, h)),
            (g, _rows(new_o, g), _rows(new_d, g), _rows(new_w, g), out_states[g]))
