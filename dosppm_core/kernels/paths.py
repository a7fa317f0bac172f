"""One bounce of a batch of photon or eye paths, after intersection.

Each kernel reads the closest hits of a batch and writes, per ray, what
happened: a deposit or a hit point, the continuing ray, and why the path
ended (codes in `dosppm_core.jobs`). Compaction is left to the caller so
that the same step serves a whole scene or one chunk.

Both kernels take the scene as one `SurfaceData` tuple and share the hit
setup: `hit_setup` (position, normal, material, side of arrival),
`sample_scatter`, `write_facing` (a hit point's normal, turned to the arriving ray)
and `write_spawn` (the spawn offset). The per-ray helpers are inlined
(inline='always') so the loops hold no calls, and each kernel hands
blocks of rows to a function that unpacks the tuples once per block.
The photon bounce's block and packing functions are inlined too: compiled
apart, they cost that kernel 4-7% (`benchmarks/kernels.py --against`
times both kernels, call by call, against the code before this split).
"""
import math
from typing import NamedTuple

import numba as nb
import numpy as np

from dosppm_core.jobs import ABSORBED, CONTINUES, ESCAPED, MAX_DEPTH, STORED
from dosppm_core.kernels.anisotropic import scatter
from dosppm_core.kernels.bsdf import is_specular, sample_bsdf
from dosppm_core.kernels.materials import (
    B_ANISO,
    B_BUMP_MAP,
    B_CHOICE,
    B_NORMAL_MAP,
    B_OPACITY,
    bsdf_rows,
    is_coloured,
    is_transmissive,
    plastic_specular_probability,
    resolve_surface,
    sample_colour,
    side_float,
)
from dosppm_core.scene.model import PLASTIC, ROUGH_DIELECTRIC
from dosppm_core.kernels.rng import next_float
from dosppm_core.kernels.shading import is_mapped, photon_shading
from dosppm_core.kernels.smooth import arrival_factor, smooth_adjoint, smooth_normal
from dosppm_core.kernels.texture import texel_at

# `prim` of a ray whose hit lies in another chunk (it left through a
# portal): the bounce kernels skip its row, so a chunk's batch need not be
# split and copied before each bounce; only the leaving rows are moved.
ELSEWHERE = -2
SKIPPED = -1    # its end code: counted nowhere, output nowhere
FLAT, MAPPED, SMOOTH = 0, 1, 2      # where a photon's shading normal comes from (`_photon_normal`)


class SurfaceData(NamedTuple):
    """The arrays the bounce kernels read: geometry and materials. A named
    tuple, so a kernel takes the whole scene as one argument."""
    vertices: np.ndarray        # float32 (V, 3)
    triangles: np.ndarray       # (T, 3) vertex rows
    tri_material: np.ndarray    # (T,) material of each triangle
    kind: np.ndarray            # per material: DIFFUSE, MIRROR, GLASS, GLOSSY
    reflectance: np.ndarray     # (M, 3)
    emission: np.ndarray        # (M, 3)
    ior: np.ndarray
    roughness: np.ndarray       # GGX alpha
    two_sided: np.ndarray
    eps_abs: float              # absolute part of the spawn offset (Scene.spawn_epsilon)
    bsdf: np.ndarray            # (M, B_COLS) float64: materials.bsdf_rows, for the coloured kinds
    # Textures (`kernels.texture`): empty arrays in an untextured scene.
    uvs: np.ndarray             # float32 (V, 2) or (0, 2)
    mat_texture: np.ndarray     # int32 (M,): the texture giving reflectance, -1 for none
    tex_info: np.ndarray        # int32 (K, 6), `TextureTable.info`
    tex_uv: np.ndarray          # float64 (K, 6), its to_uv maps
    texels: np.ndarray          # float32 (N, 3)
    # Textured area lights: the texture (of the LightTable's own) that
    # multiplies each material's emission, -1 for none, and those textures.
    emission_texture: np.ndarray    # int32 (M,)
    light_tex_info: np.ndarray
    light_tex_uv: np.ndarray
    light_texels: np.ndarray
    # Smooth meshes' vertex normals (`kernels.smooth`): float32 (V, 3), or
    # (0, 3) in a scene of flat meshes only.
    normals: np.ndarray

    @classmethod
    def from_scene(cls, scene) -> "SurfaceData":
        return cls.from_arrays(scene.vertices, scene.triangles, scene.tri_material, scene.materials,
                               scene.spawn_epsilon(), scene.uvs, scene.textures, scene.lights, scene.normals)

    @classmethod
    def from_arrays(cls, vertices, triangles, tri_material, m, eps_abs, uvs, textures,
                    lights=None, normals=None) -> "SurfaceData":
        """From geometry arrays, a `MaterialTable` m, a `TextureTable`,
        the `LightTable` (its textures; None: no textured area lights) and
        the vertex normals (None: no smooth meshes)."""
        etex = np.ascontiguousarray(m.emission_texture, np.int32)
        light_textures = (np.zeros((0, 6), np.int32), np.zeros((0, 6)), np.zeros((0, 3), np.float32))
        if lights is not None and len(lights.tex_info):
            light_textures = (lights.tex_info, lights.tex_uv, lights.tex_texels)
        else:
            etex = np.full(len(m.kind), -1, np.int32)
        return cls(vertices, triangles, tri_material, m.kind, m.reflectance, m.emission, m.ior,
                   m.roughness, m.two_sided, eps_abs, bsdf_rows(m), np.ascontiguousarray(uvs, np.float32),
                   np.ascontiguousarray(m.texture, np.int32), textures.info, textures.uv_map,
                   textures.texels, etex, *light_textures,
                   np.ascontiguousarray(np.zeros((0, 3)) if normals is None else normals, np.float32))

    @property
    def textured(self) -> bool:
        return _flags(self)[0]

    @property
    def anisotropic(self) -> bool:
        """Whether a material needs a tangent frame (`kernels.anisotropic`)."""
        return _flags(self)[1]

    @property
    def smooth_normals(self):
        """`normals`, or None in a scene of flat meshes only: the eye bounce
        is compiled for that None without the smooth meshes' lookups."""
        return self.normals if len(self.normals) else None

    @property
    def material_extras(self):
        """`bsdf`, or None where every material is of a plain kind (diffuse,
        mirror, glass, glossy: not `materials.is_coloured`), none a mask or
        a blend, textured or normal- or bump-mapped: the bounces are
        compiled for that None without those branches (measured: 10% of a
        plain scene's eye bounce, a third of its photon bounce)."""
        return None if _flags(self)[3] else self.bsdf

    @property
    def shading_mapped(self) -> bool:
        """Whether a material has a normal or bump map (`kernels.shading`)."""
        return _flags(self)[2]


# id(bsdf) -> (bsdf, kind, mat_texture, flags): the flags of a materials
# table, computed once. The bounces and the direct light ask for them at
# every call, and computing them took about 40 us a call: 1.5% of a plain
# scene's one-process render, where the eye bounce is called a hundred
# times an iteration. The entry holds the arrays it read, so an id is
# never taken for another table's.
_FLAG_CACHE: dict = {}
_FLAG_CACHE_SIZE = 64


def _flags(surf: SurfaceData) -> tuple:
    """(textured, anisotropic, shading mapped, plain) of `surf`'s materials."""
    hit = _FLAG_CACHE.get(id(surf.bsdf))
    if hit is not None and hit[0] is surf.bsdf and hit[1] is surf.kind and hit[2] is surf.mat_texture:
        return hit[3]
    bsdf = surf.bsdf
    textured = bool(np.any(surf.mat_texture >= 0))
    mapped = bool(np.any(bsdf[:, B_NORMAL_MAP] >= 0) or np.any(bsdf[:, B_BUMP_MAP] >= 0))
    plain = bool(np.all(surf.kind < ROUGH_DIELECTRIC) and not np.any(bsdf[:, B_CHOICE] > 0.0)
                 and not textured and not mapped)
    flags = (textured, bool(np.any(bsdf[:, B_ANISO] > 0)), mapped, plain)
    if len(_FLAG_CACHE) >= _FLAG_CACHE_SIZE:
        _FLAG_CACHE.clear()
    _FLAG_CACHE[id(bsdf)] = (bsdf, surf.kind, surf.mat_texture, flags)
    return flags


@nb.njit(cache=True, error_model="numpy")
def surface(x0, y0, z0, x1, y1, z1, x2, y2, z2, u, v):
    """Hit position (from barycentrics, float64: more exact than o + t d)
    and the unit CCW geometric normal, from the triangle's vertices
    (scalars: a call taking arrays would reference-count them per ray)."""
    w = 1.0 - u - v
    p0 = w * np.float64(x0) + u * np.float64(x1) + v * np.float64(x2)
    p1 = w * np.float64(y0) + u * np.float64(y1) + v * np.float64(y2)
    p2 = w * np.float64(z0) + u * np.float64(z1) + v * np.float64(z2)
    a0, a1, a2 = np.float64(x1) - x0, np.float64(y1) - y0, np.float64(z1) - z0
    b0, b1, b2 = np.float64(x2) - x0, np.float64(y2) - y0, np.float64(z2) - z0
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


# -- the hit setup both bounces share (inlined: called once per ray) -----------
@nb.njit(inline="always", cache=True, error_model="numpy")
def hit_setup(verts, tris, tri_material, kinds, tri, u, v, d0, d1, d2):
    """Everything about the hit of a ray of direction d on triangle `tri`
    at barycentrics (u, v): position p, unit geometric normal n, the
    direction back along the ray w = -d, the material and its kind, and
    whether the ray arrived on the front (the CCW side)."""
    t0, t1, t2 = tris[tri, 0], tris[tri, 1], tris[tri, 2]
    p0, p1, p2, n0, n1, n2 = surface(
        verts[t0, 0], verts[t0, 1], verts[t0, 2], verts[t1, 0], verts[t1, 1], verts[t1, 2],
        verts[t2, 0], verts[t2, 1], verts[t2, 2], np.float64(u), np.float64(v))
    w0, w1, w2 = -d0, -d1, -d2
    m = tri_material[tri]
    front = n0 * w0 + n1 * w1 + n2 * w2 > 0.0
    return p0, p1, p2, n0, n1, n2, w0, w1, w2, m, kinds[m], front


@nb.njit(inline="always", cache=True, error_model="numpy")
def sample_scatter(two_sided, ior, rough, refl, bsdf, extras, m, kind, n0, n1, n2, w0, w1, w2,
                   u1, u2, u3, radiance):
    """`sample_bsdf` (or `materials.sample_colour`, never with `extras`
    None: `SurfaceData.material_extras`) with material m's parameters.
    Returns (ok, direction, throughput rgb, eta_scale): the path's weight
    is multiplied by throughput * eta_scale, where eta_scale is the eta^2
    of radiance refracted (Russian roulette ignores it)."""
    if extras is not None and is_coloured(kind):
        if not is_transmissive(kind) and n0 * w0 + n1 * w1 + n2 * w2 < 0.0:
            if not two_sided[m]:
                return False, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0
            n0, n1, n2 = -n0, -n1, -n2
        ok, d0, d1, d2, t0, t1, t2, eta_scale, _delta = sample_colour(
            kind, bsdf[m], n0, n1, n2, w0, w1, w2, u1, u2, u3, radiance)
        return ok, d0, d1, d2, t0, t1, t2, eta_scale
    ok, d0, d1, d2, scale, _spec = sample_bsdf(kind, two_sided[m], np.float64(ior[m]),
                                               np.float64(rough[m]), n0, n1, n2, w0, w1, w2,
                                               u1, u2, u3, radiance)
    k, eta_scale = (1.0, scale) if radiance else (scale, 1.0)
    return ok, d0, d1, d2, refl[m, 0] * k, refl[m, 1] * k, refl[m, 2] * k, eta_scale


@nb.njit(inline="always", cache=True, error_model="numpy")
def write_facing(pos, nrm, row, p0, p1, p2, n0, n1, n2, front):
    """Store a point of a non-specular surface and its normal turned
    towards the arriving ray (a two-sided surface hit from behind)."""
    s = 1.0 if front else -1.0
    pos[row, 0], pos[row, 1], pos[row, 2] = p0, p1, p2
    nrm[row, 0], nrm[row, 1], nrm[row, 2] = s * n0, s * n1, s * n2


@nb.njit(inline="always", cache=True, error_model="numpy")
def write_spawn(org, dirn, row, p0, p1, p2, n0, n1, n2, d0, d1, d2, eps_rel, eps_abs):
    """Store the continuing ray: its origin off the surface on the side of
    the sampled direction d, and d normalised."""
    dl = math.sqrt(d0 * d0 + d1 * d1 + d2 * d2)
    dirn[row, 0], dirn[row, 1], dirn[row, 2] = d0 / dl, d1 / dl, d2 / dl
    org[row, 0], org[row, 1], org[row, 2] = offset_origin(
        p0, p1, p2, n0, n1, n2, d0, d1, d2, eps_rel, eps_abs)


@nb.njit(inline="always", cache=True, error_model="numpy")
def outside(box, p0, p1, p2):
    return (p0 < box[0, 0] or p0 > box[1, 0] or p1 < box[0, 1] or p1 > box[1, 1]
            or p2 < box[0, 2] or p2 > box[1, 2])


# Past this many surfaces a path survives each bounce with probability at
# most DEEP_SURVIVAL. Roulette on the throughput alone keeps every path
# through lossless glass, and light trapped in it by total internal
# reflection then bounced to the depth limit: on cornell-glass the eye
# passes' tail of such paths took 256 nearly empty steps, halving hit
# points/s. Reweighted by 1/p, this stays unbiased.
DEEP_DEPTH = 8
DEEP_SURVIVAL = 0.9


@nb.njit(cache=True, error_model="numpy")
def tinted(t0, t1, t2, texture, uvs, tris, tinfo, tuv, texels, tri, u, v, extras=0):
    """A bounce's throughput t times the texel at the hit when its material
    is textured (`texture` >= 0; its reflectance row is white then). With
    `extras` None (`SurfaceData.material_extras`) none is."""
    if extras is None or texture < 0:
        return t0, t1, t2
    x0, x1, x2 = texel_at(uvs, tris, tinfo, tuv, texels, texture, tri, u, v)
    return t0 * x0, t1 * x1, t2 * x2


@nb.njit(inline="always", cache=True, error_model="numpy")
def roulette(flux, i, t0, t1, t2, ur, depth):
    """Russian roulette on the scattered flux (or an eye path's weight)
    flux * t: a path survives with the ratio p of its new to old largest
    component (at most DEEP_SURVIVAL from surface DEEP_DEPTH on), and is
    reweighted by 1/p. Returns (survives, the new flux). Unbiased, so the
    depth limit is only a safety net. An eye path's roulette decides on its
    throughput alone, not the eta^2 of refraction (pbrt's etaScale): that
    factor leaving glass would kill 56% of the paths through it."""
    old_max = max(flux[i, 0], flux[i, 1], flux[i, 2])
    nf0 = flux[i, 0] * t0
    nf1 = flux[i, 1] * t1
    nf2 = flux[i, 2] * t2
    p = min(1.0, max(nf0, nf1, nf2) / old_max) if old_max > 0 else 0.0
    if depth >= DEEP_DEPTH:
        p = min(p, DEEP_SURVIVAL)
    if ur < 1.0 - p:            # dies with probability 1 - p
        return False, 0.0, 0.0, 0.0
    keep = 1.0 / p
    return True, nf0 * keep, nf1 * keep, nf2 * keep


# -- batch plumbing ------------------------------------------------------------
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


@nb.njit(cache=True, error_model="numpy")
def _deposit_rows(n):
    """position, incoming, flux, job"""
    return (np.empty((n, 3), np.float32), np.empty((n, 3), np.float32),
            np.empty((n, 3), np.float32), np.empty(n, np.int64))


@nb.njit(cache=True, error_model="numpy")
def _path_rows(n):
    """origin, direction, flux, rng state, depth, job, pixel"""
    return (np.empty((n, 3), np.float32), np.empty((n, 3), np.float32),
            np.empty((n, 3), np.float32), np.empty(n, np.uint64), np.empty(n, np.int32),
            np.empty(n, np.int64), np.empty(n, np.int32))


# -- the photon bounce -----------------------------------------------------------
@nb.njit(cache=True, parallel=True, error_model="numpy")
def scatter_photons(rays, hits, surf, normals, extras, cull_box, max_depth, deposit_from, eps_rel):
    """Deposit photons at non-specular hits (if inside `cull_box`, rows lo
    and hi, and from surface `deposit_from` on: 1 when direct light comes
    from shadow rays, 0 for the paper's pure estimator) and scatter them
    with Russian roulette. `rays` is
    (direction, flux, depth, rng state, job, pixel), `hits` (prim, u, v).
    Returns (end counts, culled count, deposits (position, incoming,
    flux, job), continuing paths (origin, direction, flux, rng
    state, depth, job, pixel)). `normals` and `extras` are
    `surf.smooth_normals` and `surf.material_extras`, as for the eye
    bounce: None compiles the loop without those branches.

    Compaction is done here, in blocks: each block of rows writes its
    deposits and survivors densely from its own start, then one parallel
    pass packs the blocks. A mask-then-gather compaction (or numpy's
    boolean indexing) cost as much as the bounce itself."""
    n = hits[0].shape[0]
    nblk = max(1, min(64, n // 2048))   # enough blocks to balance threads
    end = np.empty(n, np.int8)
    culled = np.zeros(n, np.bool_)
    dep = _deposit_rows(n)
    nxt = _path_rows(n)
    counts = np.zeros((nblk, 2), np.int64)
    for b in nb.prange(nblk):
        a = b * n // nblk
        dc, gc = _scatter_block(a, (b + 1) * n // nblk, rays, hits, surf, normals, extras, cull_box,
                                max_depth, deposit_from, eps_rel, end, culled, dep, nxt)
        counts[b, 0] = dc - a
        counts[b, 1] = gc - a
    out_dep, out_nxt = _pack_blocks(counts, n, dep, nxt)
    return _ends(end), int(culled.sum()), out_dep, out_nxt


@nb.njit(inline="always", cache=True, error_model="numpy")
def _scatter_block(a, e, rays, hits, surf, normals, extras, cull_box, max_depth, deposit_from, eps_rel,
                   end, culled, dep, nxt):
    """The photon bounce of rows [a, e), deposits and continuing paths written densely
    from row a; returns (dc, gc). Tuples unpacked once per block, not per ray."""
    direction, flux, depth, states, job, pixel = rays
    (verts, tris, tri_mat, kinds, refl, _emit, ior, rough, two_sided, eps_abs, bsdf,
     uvs, mtex, tinfo, tuv, texels, _etex, _ltinfo, _ltuv, _ltexels, _normals) = surf
    prim, u, v = hits
    dep_pos, dep_in, dep_f, dep_job = dep
    new_o, new_d, new_f, new_st, new_depth, new_job, new_pix = nxt
    dc, gc = a, a
    for i in range(a, e):
        tri = prim[i]
        if tri < 0:
            end[i] = ESCAPED if tri != ELSEWHERE else SKIPPED
            continue
        p0, p1, p2, n0, n1, n2, w0, w1, w2, m, kind, front = hit_setup(
            verts, tris, tri_mat, kinds, tri, u[i], v[i], direction[i, 0], direction[i, 1], direction[i, 2])
        st = states[i]
        mapped, s0, s1, s2, k_in = _photon_normal(surf, normals, extras, m, tri, u[i], v[i], n0, n1, n2,
                                                  front, w0, w1, w2)
        if not is_specular(kind) and (front or two_sided[m]) and k_in > 0.0 and depth[i] >= deposit_from:
            if outside(cull_box, p0, p1, p2):   # (before deposit_from shadow rays bring direct light)
                culled[i] = True
            else:
                _deposit(dep_pos, dep_in, dep_f, dep_job, dc, p0, p1, p2, direction, flux, job, i, k_in)
                dc += 1
        if extras is not None and bsdf[m, B_CHOICE] > 0.0:    # a mask or a blend (draws only here)
            st, m, gc = _photon_choice(i, gc, m, tri, u[i], v[i], st, p0, p1, p2, n0, n1, n2, w0, w1, w2,
                                       rays, surf, max_depth, eps_rel, end, nxt)
            if m < 0:
                continue
            kind = kinds[m]
            mapped, s0, s1, s2, k_in = _photon_normal(surf, normals, extras, m, tri, u[i], v[i], n0, n1, n2,
                                                      front, w0, w1, w2)
        if not is_specular(kind) and (not (front or two_sided[m]) or not k_in > 0.0):
            end[i] = ABSORBED
            continue
        if depth[i] + 1 >= max_depth:
            end[i] = MAX_DEPTH
            continue
        st, u1, u2, u3, ur = _four_floats(st)
        ok, d0, d1, d2, t0, t1, t2 = _photon_scatter(surf, extras, m, kind, tri, u[i], v[i], mapped, s0, s1, s2,
                                                     k_in, n0, n1, n2, front, w0, w1, w2, u1, u2, u3)
        if not ok:
            end[i] = ABSORBED
            continue
        t0, t1, t2 = tinted(t0, t1, t2, mtex[m], uvs, tris, tinfo, tuv, texels, tri, u[i], v[i], extras)
        ok, f0, f1, f2 = roulette(flux, i, t0, t1, t2, ur, depth[i])
        if not ok:
            end[i] = ABSORBED
            continue
        new_f[gc, 0], new_f[gc, 1], new_f[gc, 2] = f0, f1, f2
        write_spawn(new_o, new_d, gc, p0, p1, p2, n0, n1, n2, d0, d1, d2, eps_rel, eps_abs)
        new_st[gc], new_depth[gc], new_job[gc], new_pix[gc] = st, depth[i] + 1, job[i], pixel[i]
        gc += 1
        end[i] = CONTINUES
    return dc, gc


@nb.njit(inline="always", cache=True, error_model="numpy")
def _photon_normal(surf, normals, extras, m, tri, u, v, n0, n1, n2, front, w0, w1, w2):
    """(FLAT, MAPPED or SMOOTH, shading normal s, Veach's factor k_in) of
    material m at the hit: a normal or bump map's (`kernels.shading`: s
    facing the photon), a smooth mesh's (`kernels.smooth`: s on the
    winding's side), else the geometric normal and 1. `normals` or
    `extras` None: numba prunes those lookups at compile time."""
    if extras is None or not is_mapped(surf.bsdf, m):
        if normals is None:
            return FLAT, n0, n1, n2, 1.0
        smooth, s0, s1, s2 = smooth_normal(normals, surf.triangles, tri, np.float64(u), np.float64(v),
                                           n0, n1, n2, w0, w1, w2)
        if smooth:
            return SMOOTH, s0, s1, s2, arrival_factor(n0, n1, n2, s0, s1, s2, w0, w1, w2)
        return FLAT, n0, n1, n2, 1.0
    tex = (surf.uvs, surf.triangles, surf.tex_info, surf.tex_uv, surf.texels)
    s0, s1, s2, k_in = photon_shading(surf.bsdf, m, surf.vertices, tex, tri, u, v, n0, n1, n2, front,
                                      w0, w1, w2)
    return MAPPED, s0, s1, s2, k_in


@nb.njit(inline="always", cache=True, error_model="numpy")
def _photon_scatter(surf, extras, m, kind, tri, u, v, mapped, s0, s1, s2, k_in, n0, n1, n2, front, w0, w1, w2,
                    u1, u2, u3):
    """A photon's `sample_scatter` about its (shading) normal s, or an
    anisotropic conductor's lobe in the surface's frame there
    (`kernels.anisotropic`), made Veach's adjoint where s is not the
    geometric normal n (`_adjoint`). Returns (ok, direction, throughput rgb)."""
    if extras is not None and surf.bsdf[m, B_ANISO] > 0.0:
        ok, d0, d1, d2, t0, t1, t2 = scatter(surf, m, tri, u, v, s0, s1, s2, w0, w1, w2, u2, u3)
    else:
        ok, d0, d1, d2, t0, t1, t2, _es = sample_scatter(
            surf.two_sided, surf.ior, surf.roughness, surf.reflectance, surf.bsdf, extras, m, kind,
            s0, s1, s2, w0, w1, w2, u1, u2, u3, False)
    if ok and mapped != FLAT:
        ok, t0, t1, t2 = _adjoint(mapped, t0, t1, t2, k_in, n0, n1, n2, s0, s1, s2, d0, d1, d2, front)
    return ok, d0, d1, d2, t0, t1, t2


@nb.njit(inline="always", cache=True, error_model="numpy")
def _deposit(dep_pos, dep_in, dep_f, dep_job, dc, p0, p1, p2, direction, flux, job, i, k_in):
    """Row dc of the deposits: photon i at p, from -direction, its flux
    times k_in. No normal: the gather counts a photon by the hit point's side."""
    dep_pos[dc, 0], dep_pos[dc, 1], dep_pos[dc, 2] = p0, p1, p2
    for k in range(3):
        dep_in[dc, k], dep_f[dc, k] = -direction[i, k], flux[i, k] * k_in
    dep_job[dc] = job[i]


@nb.njit(inline="always", cache=True, error_model="numpy")
def _four_floats(st):
    """(state, u1, u2, u3, u_roulette): a photon bounce's draws."""
    st, u1 = next_float(st)
    st, u2 = next_float(st)
    st, u3 = next_float(st)
    st, ur = next_float(st)
    return st, u1, u2, u3, ur


@nb.njit(cache=True, error_model="numpy")
def _adjoint(mapped, t0, t1, t2, k_in, n0, n1, n2, s0, s1, s2, d0, d1, d2, front):
    """A photon's throughput t = f |d.ns| / p at a MAPPED hit, made Veach's
    adjoint: times k_in |d.ng| / |d.ns| (`kernels.shading`); at a SMOOTH
    one `smooth.smooth_adjoint`'s. Returns (ok, t)."""
    if mapped == SMOOTH:
        return smooth_adjoint(t0, t1, t2, k_in, n0, n1, n2, s0, s1, s2, d0, d1, d2)
    g = 1.0 if front else -1.0
    cg = g * (d0 * n0 + d1 * n1 + d2 * n2)
    cs = d0 * s0 + d1 * s1 + d2 * s2
    if not (cg > 0.0 and cs > 0.0):
        return False, 0.0, 0.0, 0.0
    k = k_in * cg / cs
    return True, t0 * k, t1 * k, t2 * k


@nb.njit(cache=True, error_model="numpy")
def _photon_choice(i, gc, m, tri, u, v, st, p0, p1, p2, n0, n1, n2, w0, w1, w2, rays, surf, max_depth,
                   eps_rel, end, nxt):
    """What photon i meets at a mask or blend (`materials.resolve_surface`):
    (state, the material that scatters or -1 when it passed through, the
    next free row of `nxt`). Its deposit came first: it records the flux
    arriving here, whatever the hit point gathering it chose."""
    st, m, through = resolve_surface(surf.bsdf, m, st, False, surf.uvs, surf.triangles, surf.tex_info,
                                     surf.tex_uv, surf.texels, tri, u, v)
    if not through:
        return st, m, gc
    return st, -1, _photon_pass_through(i, gc, st, p0, p1, p2, n0, n1, n2, w0, w1, w2, rays, max_depth,
                                        eps_rel, surf.eps_abs, end, nxt)


@nb.njit(cache=True, error_model="numpy")
def _photon_pass_through(i, gc, st, p0, p1, p2, n0, n1, n2, w0, w1, w2, rays, max_depth, eps_rel,
                         eps_abs, end, nxt):
    """Photon i goes on straight through a mask's hole, as one bounce (so
    a photon lighting a floor through leaves is deposited there: shadow
    rays stop at masks). Returns the next free row of `nxt`. Not inlined:
    numba's inliner bound this body's unpacked `flux` to the caller's
    `direction` (garbage flux through masks); the call is rare anyway."""
    _direction, flux, depth, _states, job, pixel = rays
    new_o, new_d, new_f, new_st, new_depth, new_job, new_pix = nxt
    if depth[i] + 1 >= max_depth:
        end[i] = MAX_DEPTH
        return gc
    new_f[gc, 0], new_f[gc, 1], new_f[gc, 2] = flux[i, 0], flux[i, 1], flux[i, 2]
    write_spawn(new_o, new_d, gc, p0, p1, p2, n0, n1, n2, -w0, -w1, -w2, eps_rel, eps_abs)
    new_st[gc], new_depth[gc], new_job[gc], new_pix[gc] = st, depth[i] + 1, job[i], pixel[i]
    end[i] = CONTINUES
    return gc + 1


@nb.njit(inline="always", cache=True, error_model="numpy")
def _pack_blocks(counts, n, dep, nxt):
    """Pack the deposits and continuing paths that `scatter_photons`
    wrote per block (block b's from its first row) into dense arrays.
    Inlined into the parallel kernel, where its prange runs in parallel."""
    nblk = counts.shape[0]
    ds = _block_starts(counts, 0)
    gs = _block_starts(counts, 1)
    dep_pos, dep_in, dep_f, dep_job = dep
    new_o, new_d, new_f, new_st, new_depth, new_job, new_pix = nxt
    out_dep = _deposit_rows(ds[nblk])
    out_nxt = _path_rows(gs[nblk])
    o_pos, o_in, o_f, o_job = out_dep
    c_o, c_d, c_f, c_st, c_depth, c_job, c_pix = out_nxt
    for b in nb.prange(nblk):
        a = b * n // nblk
        for j in range(counts[b, 0]):
            o = ds[b] + j
            for k in range(3):
                o_pos[o, k] = dep_pos[a + j, k]
                o_in[o, k] = dep_in[a + j, k]
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
    return out_dep, out_nxt


# -- the eye bounce --------------------------------------------------------------
# Below this many rays an eye bounce runs on one thread: a parallel call
# costs its launches (the kernel's and its row gathers') whatever its size,
# and an eye pass ends in dozens of steps of a few paths each (light caught
# in glass). On a 2M-triangle building with glass at 160x120 the steps below
# 2,048 rays were 77% of the calls.
SERIAL_BELOW = 2048


@nb.njit(cache=True, parallel=True, error_model="numpy")
def advance_eye_paths(rays, hits, surf, normals, extras, max_depth, eps_rel):
    """Record emission seen along eye paths, store a hit point at the first
    non-specular surface, and continue through mirrors and glass. `rays`
    is (direction, weight, depth, rng state), `hits` (prim, u, v). Returns
    (end counts, emission (index into the batch, rgb), hit points (index,
    position, normal, material), continuing paths (index, origin,
    direction, weight, rng state)); a hit point's outgoing direction is
    -direction and its material tri_material[prim], or the part a mask or
    blend chose there. `normals` is `surf.smooth_normals` and `extras`
    `surf.material_extras`: None in a flat scene or one of plain materials,
    whose loop numba then compiles without those branches (run-time checks
    made the flat bounce 1.35x slower, plain materials' 1.1x).
    (`advance_eye_paths_serial`: the same on one thread.)"""
    n = hits[0].shape[0]
    nblk = max(1, min(64, n // 2048))   # enough blocks to balance threads
    end, emitted, hp, nxt = _eye_buffers(n, rays)
    for b in nb.prange(nblk):
        _advance_block(b * n // nblk, (b + 1) * n // nblk, rays, hits, surf, normals, extras, max_depth,
                       eps_rel, end, emitted, hp, nxt)
    return _eye_outputs(end, emitted, hp, nxt)


@nb.njit(cache=True, error_model="numpy")
def advance_eye_paths_serial(rays, hits, surf, normals, extras, max_depth, eps_rel):
    """`advance_eye_paths` on this thread, for small batches."""
    n = hits[0].shape[0]
    end, emitted, hp, nxt = _eye_buffers(n, rays)
    _advance_block(0, n, rays, hits, surf, normals, extras, max_depth, eps_rel, end, emitted, hp, nxt)
    return _eye_outputs(end, emitted, hp, nxt)


@nb.njit(cache=True, error_model="numpy")
def _eye_buffers(n, rays):
    end = np.empty(n, np.int8)
    emitted = np.zeros((n, 3), np.float32)
    hp = (np.empty((n, 3), np.float32), np.empty((n, 3), np.float32), np.empty(n, np.int32))
    nxt = (np.empty((n, 3), np.float32), np.empty((n, 3), np.float32),
           np.empty((n, 3), np.float32), rays[3].copy())
    return end, emitted, hp, nxt


@nb.njit(cache=True, error_model="numpy")
def _eye_outputs(end, emitted, hp, nxt):
    lit = _indices((emitted[:, 0] + emitted[:, 1] + emitted[:, 2]) > 0.0)
    h = _indices(end == STORED)
    g = _indices(end == CONTINUES)
    return (_ends(end), (lit, _take_rows(emitted, lit)),
            (h, _take_rows(hp[0], h), _take_rows(hp[1], h), hp[2][h]),
            (g, _take_rows(nxt[0], g), _take_rows(nxt[1], g), _take_rows(nxt[2], g), nxt[3][g]))


@nb.njit(cache=True, error_model="numpy")
def _take_rows(a, idx):
    """a[idx] (rows of a few floats: a thread copies them faster than a
    parallel launch would)."""
    out = np.empty((idx.shape[0], a.shape[1]), a.dtype)
    for j in range(idx.shape[0]):
        for k in range(a.shape[1]):
            out[j, k] = a[idx[j], k]
    return out


# Depth: a path has `depth` scattering events behind it; a hit point, or going
# on through a mirror, glass or a mask's hole, adds one. At max_depth only the
# emission counts (Mitsuba's last vertex: the light seen in a mirror).
@nb.njit(cache=True, error_model="numpy")
def _advance_block(a, e, rays, hits, surf, normals, extras, max_depth, eps_rel, end, emitted, hp, nxt):
    """The eye bounce of rows [a, e), each written to its own row. Tuples unpacked once per block."""
    direction, weight, depth, states = rays
    (verts, tris, tri_mat, kinds, refl, emit, ior, rough, two_sided, eps_abs, bsdf,
     uvs, mtex, tinfo, tuv, texels, _etex, _ltinfo, _ltuv, _ltexels, _normals) = surf
    prim, u, v = hits
    hp_pos, hp_n, hp_mat = hp
    new_o, new_d, new_w, new_st = nxt
    for i in range(a, e):
        tri = prim[i]
        if tri < 0:
            end[i] = ESCAPED if tri != ELSEWHERE else SKIPPED
            continue
        p0, p1, p2, n0, n1, n2, w0, w1, w2, m, kind, front = hit_setup(
            verts, tris, tri_mat, kinds, tri, u[i], v[i], direction[i, 0], direction[i, 1], direction[i, 2])
        if front:  # one-sided emitters, as in Mitsuba
            for k in range(3):
                emitted[i, k] = weight[i, k] * emit[m, k]
        if extras is not None and bsdf[m, B_CHOICE] > 0.0:     # a mask or a blend: what is there
            m = _eye_choice(i, m, tri, u[i], v[i], p0, p1, p2, n0, n1, n2, w0, w1, w2, rays, surf,
                            max_depth, eps_rel, end, nxt)
            if m < 0:
                continue
            kind = kinds[m]
        hp_mat[i], coat = m, False
        s0, s1, s2 = _eye_normal(bsdf, normals, tris, m, tri, u[i], v[i], n0, n1, n2, w0, w1, w2)
        if not is_specular(kind):
            if not front and not two_sided[m]:
                end[i] = ABSORBED
                continue
            if extras is not None and kind == PLASTIC:     # the coating's mirror with probability q
                s = 1.0 if front else -1.0
                coat = side_float(states[i], 1) < plastic_specular_probability(
                    bsdf[m], s * s0, s * s1, s * s2, w0, w1, w2)
            if not coat and depth[i] < max_depth:
                # A rough dielectric's hit point keeps its normal on the winding's side: the side decides eta.
                write_facing(hp_pos, hp_n, i, p0, p1, p2, s0, s1, s2, front or is_transmissive(kind))
                end[i] = STORED
                continue
        if depth[i] >= max_depth:
            end[i] = MAX_DEPTH
            continue
        st, u1 = next_float(states[i])
        st, ur = next_float(st)
        new_st[i] = st
        ok, d0, d1, d2, t0, t1, t2, eta_scale = sample_scatter(
            two_sided, ior, rough, refl, bsdf, extras, m, kind, s0, s1, s2, w0, w1, w2,
            0.0 if coat else u1, 0.5, 0.5, True)
        if not ok:
            end[i] = ABSORBED
            continue
        # Russian roulette as for photons (`roulette`: why not on refraction's eta^2).
        t0, t1, t2 = tinted(t0, t1, t2, mtex[m], uvs, tris, tinfo, tuv, texels, tri, u[i], v[i], extras)
        ok, f0, f1, f2 = roulette(weight, i, t0, t1, t2, ur, depth[i])
        if not ok:
            end[i] = ABSORBED
            continue
        new_w[i, 0], new_w[i, 1], new_w[i, 2] = f0 * eta_scale, f1 * eta_scale, f2 * eta_scale
        write_spawn(new_o, new_d, i, p0, p1, p2, n0, n1, n2, d0, d1, d2, eps_rel, eps_abs)
        end[i] = CONTINUES


@nb.njit(inline="always", cache=True, error_model="numpy")
def _eye_normal(bsdf, normals, tris, m, tri, u, v, n0, n1, n2, w0, w1, w2):
    """An eye path's shading normal at the hit: a smooth mesh's
    (`kernels.smooth`), else the geometric n (a normal or bump map
    perturbs its hit points afterwards: `shading.perturb_hit_points`).
    `normals` None (a flat scene): numba prunes the lookups at compile time."""
    if normals is None or is_mapped(bsdf, m):
        return n0, n1, n2
    _smooth, s0, s1, s2 = smooth_normal(normals, tris, tri, np.float64(u), np.float64(v),
                                        n0, n1, n2, w0, w1, w2)
    return s0, s1, s2


@nb.njit(cache=True, error_model="numpy")
def _eye_choice(i, m, tri, u, v, p0, p1, p2, n0, n1, n2, w0, w1, w2, rays, surf, max_depth, eps_rel, end,
                nxt):
    """What eye path i meets at a mask or blend (`materials.resolve_surface`,
    from the path's side stream): the material that scatters, or -1 when
    the path went on through."""
    direction, weight, depth, states = rays
    _st, m, through = resolve_surface(surf.bsdf, m, states[i], True, surf.uvs, surf.triangles, surf.tex_info,
                                      surf.tex_uv, surf.texels, tri, u, v)
    if not through:
        return m
    _pass_through(i, p0, p1, p2, n0, n1, n2, w0, w1, w2, depth, states, weight, max_depth,
                  eps_rel, surf.eps_abs, end, nxt)
    return -1


@nb.njit(cache=True, error_model="numpy")
def _pass_through(i, p0, p1, p2, n0, n1, n2, w0, w1, w2, depth, states, weight, max_depth,
                  eps_rel, eps_abs, end, nxt):
    """Eye path i goes on straight through a mask's hole, as one bounce."""
    new_o, new_d, new_w, new_st = nxt
    if depth[i] >= max_depth:
        end[i] = MAX_DEPTH
        return
    new_st[i] = next_float(states[i])[0]
    new_w[i, 0], new_w[i, 1], new_w[i, 2] = weight[i, 0], weight[i, 1], weight[i, 2]
    write_spawn(new_o, new_d, i, p0, p1, p2, n0, n1, n2, -w0, -w1, -w2, eps_rel, eps_abs)
    end[i] = CONTINUES
