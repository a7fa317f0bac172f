"""Tracing inside one chunk: the step every out-of-core mode repeats.

`ChunkView` is one loaded chunk (its geometry, BVH and surface arrays).
`trace_photons_in_chunk` and `trace_eye_in_chunk` follow a batch of paths
until each ends or leaves the chunk, and return the leaving rays grouped by
the chunk they enter next: OSPPM queues them in this process, the tracer
service sends them to the tracer owning that chunk. Both use the same
bounce kernels as the unchunked renderer (`tracing.scatter_photons`,
`tracing.advance_eye`), so a chunked render differs from an unchunked one
only by floating-point noise.
"""
from __future__ import annotations

import numpy as np

from dosppm_core.accel import Accelerator
from dosppm_core.chunks.portals import PORTAL_EPS, enter, intersect_in_chunk
from dosppm_core.chunks.store import ChunkGeometry
from dosppm_core.chunks.textures import chunk_surface_textures
from dosppm_core.chunks.tree import ChunkTree
from dosppm_core.jobs import ESCAPED, STORED, HitPoints, PhotonDeposits, RayBatch, ShadowRays
from dosppm_core.kernels.paths import ELSEWHERE
from dosppm_core.scene.model import SceneHeader
from dosppm_core.trace import (END_KINDS, SurfaceData, advance_eye, emit_photon_jobs, environment, escaped_light,
                               scatter_photons, shadow_results)


class ChunkView:
    """A resident chunk: BVH plus the arrays the bounce kernels read."""

    def __init__(self, index: int, geometry: ChunkGeometry, header: SceneHeader,
                 tree: ChunkTree, threads: int = 1):
        self.index, self.tree, self.geometry = index, tree, geometry
        self.eps = PORTAL_EPS * header.diagonal()
        self.total_power = header.lights.total_power    # BSDF-sampled direct-light rays weigh by it
        self.env = environment(header.lights)           # what eye paths leaving the scene see
        m, textures = chunk_surface_textures(geometry, header)
        self.surf = SurfaceData.from_arrays(geometry.vertices, geometry.triangles, geometry.tri_material,
                                            m, header.spawn_epsilon(), geometry.uv, textures, header.lights,
                                            geometry.normals)
        # An empty chunk (air between walls) still routes rays; Embree
        # needs one triangle, so give it one that no ray can reach.
        verts, tris = geometry.vertices, geometry.triangles
        if len(tris) == 0:
            far = tree.root_box[1] + 1e6 * (1 + np.abs(tree.root_box[1]))
            verts = np.array([far, far + (1, 0, 0), far + (0, 1, 0)], np.float32)
            tris = np.array([[0, 1, 2]], np.int32)
        self.accel = Accelerator(verts, tris, threads=threads)

    def intersect(self, batch, tmax=None):
        """(prim, t, u, v, next chunk, t_exit); see `portals.intersect_in_chunk`."""
        return intersect_in_chunk(self.accel, self.tree, self.index, batch.origin,
                                  batch.direction, batch.tmin, self.eps, tmax)

    def close(self) -> None:
        """Free the BVH and drop the arrays: a closed view still referenced
        somewhere (a caller's local variable) must not keep the chunk."""
        self.accel.close()
        self.geometry = self.surf = None


def route(batch: RayBatch, chunks: np.ndarray) -> dict[int, RayBatch]:
    """Split a batch by destination chunk (-1 entries must be removed first)."""
    return batch.partition(chunks)


def start_chunks(tree: ChunkTree, batch: RayBatch, keep_lost: bool = False, chunk: np.ndarray | None = None):
    """Route new rays (tmin 0) to the chunk each starts in: ({chunk: rays},
    rays that miss the scene's box altogether (escaped), as a count, or
    with `keep_lost` as a record, None if there are none). `chunk`: where
    each starts, when already located (`located_photons`)."""
    routed = route(batch, _entered(tree, batch) if chunk is None else chunk)
    lost = routed.pop(-1, None)
    if keep_lost:
        return routed, lost
    return routed, 0 if lost is None else len(lost)


def start_eye_paths(tree: ChunkTree, batch: RayBatch, env):
    """`start_chunks` for new eye rays: ({chunk: rays}, how many miss the
    scene, (pixel, rgb) those see of the environment `env`)."""
    routed, lost = start_chunks(tree, batch, keep_lost=True)
    if lost is None:
        return routed, 0, escaped_light(None, batch.slice(0, 0))
    return routed, len(lost), escaped_light(env, lost)


def _entered(tree: ChunkTree, batch: RayBatch) -> np.ndarray:
    """The chunk each new ray starts in (-1: it misses the scene), its
    tmin set to where it enters."""
    chunk, tmin = enter(tree, batch.origin, batch.direction)
    batch.tmin = np.maximum(batch.tmin, tmin)
    return chunk


def located_photons(scene, tree: ChunkTree, seed: int, keys, counts, eps_abs: float):
    """The photons of several jobs (`trace.emit_photon_jobs`, job after
    job), each with its tmin set and the chunk it starts in (-1: it misses
    the scene): a tracer emits the jobs of a photon job message at once,
    since a kernel call per 1,024-photon job costs more than its photons.
    Returns (batch, chunk)."""
    batch = emit_photon_jobs(scene, seed, keys, counts, eps_abs)
    return batch, _entered(tree, batch)


def _find_hits(view: ChunkView, batch: RayBatch):
    """Intersect; return (prim, u, v, rays leaving through portals grouped
    by next chunk). A leaving ray keeps its row with prim ELSEWHERE, which
    the bounce kernels skip: only the leaving rows are copied, resuming at
    t_exit. A miss that leaves the scene stays a miss (escaped)."""
    prim, _t, u, v, nxt, t_exit = view.intersect(batch)
    leaving = np.flatnonzero((prim < 0) & (nxt >= 0))
    if not len(leaving):
        return prim, u, v, {}
    out = batch.partition(nxt[leaving], rows=leaving, replace={"tmin": t_exit.astype(np.float32)})
    prim[leaving] = ELSEWHERE
    return prim, u, v, out


def _merge(into: dict, parts: dict) -> None:
    for k, b in parts.items():
        into.setdefault(k, []).append(b)


def _continue_here(view: ChunkView, nxt: RayBatch, outgoing: dict, counts: np.ndarray,
                   seen: list | None = None) -> RayBatch:
    """Bounced rays start where they were spawned: keep those in this chunk.
    Eye paths (`seen` a list) that leave the scene at once see the
    environment there, as the unchunked renderer's next step would."""
    routed, lost = start_chunks(view.tree, nxt, keep_lost=True)
    if lost is not None:
        counts[ESCAPED] += len(lost)
        if seen is not None and view.env is not None:
            seen.append(escaped_light(view.env, lost))
    here = routed.pop(view.index, RayBatch.empty())
    _merge(outgoing, routed)
    return here


def trace_photons_in_chunk(view: ChunkView, batch: RayBatch, cull_box, max_depth: int,
                           deposit_from: int = 0, lights: tuple | None = None):
    """Follow photons in this chunk; with `lights` (`trace.light_arrays`),
    their first hits here teach its light cache. Returns (deposits, end
    counts, culled, {chunk: [RayBatch]} of photons leaving through portals)."""
    deposits, outgoing = [], {}
    counts, culled = np.zeros(END_KINDS, np.int64), 0
    while len(batch):
        prim, u, v, out = _find_hits(view, batch)
        _merge(outgoing, out)
        dep, nxt, ends, c = scatter_photons(view.surf, batch, prim, u, v, cull_box, max_depth,
                                            deposit_from, lights)
        deposits.append(dep)
        counts += ends
        culled += c
        batch = _continue_here(view, nxt, outgoing, counts)
    counts[0] = 0
    return PhotonDeposits.concat(deposits), counts, culled, outgoing


def trace_eye_in_chunk(view: ChunkView, batch: RayBatch, max_depth: int, lights: tuple | None = None):
    """Follow eye paths in this chunk; with `lights` (`trace.light_arrays`),
    each hit point's shadow ray too, as far as this chunk. Returns (hit
    points, (pixel, rgb) of emission seen and direct light that arrived,
    end counts, {chunk: [RayBatch]} of eye paths leaving, {chunk:
    [ShadowRays]} of shadow rays leaving)."""
    hits, pix, rgb, shadows, outgoing = [], [], [], [], {}
    counts = np.zeros(END_KINDS, np.int64)
    while len(batch):
        prim, u, v, out = _find_hits(view, batch)
        _merge(outgoing, out)
        h, (p, e), nxt, ends, s = advance_eye(view.surf, batch, prim, u, v, max_depth, lights, view.env)
        hits.append(h)
        pix.append(p)
        rgb.append(e)
        shadows.append(s)
        counts += ends
        seen = []
        batch = _continue_here(view, nxt, outgoing, counts, seen)
        for p, e in seen:
            pix.append(p)
            rgb.append(e)
    shadow_out = {}
    if lights is not None:
        routed, lost = start_chunks(view.tree, ShadowRays.concat(shadows), keep_lost=True)
        if lost is not None:
            # Spawned just outside the scene's box (the top of its highest
            # surface): nothing can block them, as unchunked tracing finds.
            counts[STORED] += len(lost)
            p, e = shadow_results(lost, np.full(len(lost), -1, np.int32), np.zeros(len(lost), np.float32),
                                  view.surf, view.total_power, env=view.env)
            pix.append(p)
            rgb.append(e)
        for k, part in routed.items():
            if k != view.index:
                shadow_out.setdefault(k, []).append(part)
        (p, e), ends, out = trace_shadows_in_chunk(view, routed.get(view.index, ShadowRays.empty()))
        pix.append(p)
        rgb.append(e)
        counts += ends
        _merge(shadow_out, out)
    counts[0] = 0
    emitted = (np.concatenate(pix) if pix else np.empty(0, np.int32),
               np.concatenate(rgb) if rgb else np.empty((0, 3), np.float32))
    return HitPoints.concat(hits), emitted, counts, outgoing, shadow_out


def trace_shadows_in_chunk(view: ChunkView, shadows: ShadowRays):
    """Direct-light rays in this chunk: blocked here (or, BSDF-sampled,
    finding an emitter here), leaving through a portal before their end,
    or arrived. Returns ((pixel, rgb) of the light found, end counts
    (STORED: each ended eye path), {chunk: ShadowRays} leaving)."""
    counts = np.zeros(END_KINDS, np.int64)
    if not len(shadows):
        return (np.empty(0, np.int32), np.empty((0, 3), np.float32)), counts, {}
    prim, t, u, v, nxt, t_exit = view.intersect(shadows, shadows.tmax)
    leaving = (prim < 0) & (nxt >= 0) & (t_exit < shadows.tmax)
    rows = np.flatnonzero(leaving)
    out = {}
    if len(rows):
        out = shadows.partition(nxt[rows], rows=rows, replace={"tmin": t_exit.astype(np.float32)})
    counts[STORED] = len(shadows) - len(rows)
    return (shadow_results(shadows, prim, t, view.surf, view.total_power, ~leaving, view.env, (u, v)),
            counts, out)
