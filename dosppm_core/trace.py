"""Tracing steps: new paths, and one bounce of a batch against one
aggregate. Chunked and distributed modes call the same steps; only what
happens to the continuing rays between steps differs."""
from __future__ import annotations

from typing import NamedTuple

import numpy as np

from dosppm_core.accel import Accelerator
from dosppm_core.jobs import STORED, HitPoints, PhotonDeposits, RayBatch, ShadowRays
from dosppm_core.kernels import anisotropic, direct, emit, envmap, light_cache, paths, shading, texture
from dosppm_core.kernels.light_cache import LightCache
from dosppm_core.kernels.light_tree import build_light_tree
from dosppm_core.kernels.paths import SurfaceData
from dosppm_core.scene.model import LIGHT_DIRECTIONAL, LIGHT_ENV, LIGHT_TRIANGLE, LightTable, Scene

NO_CULL = np.array([[-np.inf] * 3, [np.inf] * 3])
EPS_REL = 2e-5   # spawn offset relative to |p|: ~300 float32 ulps
END_KINDS = 5


def emit_photon_job(scene: Scene, seed: int, job: int, count: int, eps_abs: float) -> RayBatch:
    """The `count` photons of emission job `job` (a pure function of its
    arguments, so a job can be re-emitted and traces the same photons)."""
    return emit_photon_jobs(scene, seed, [job], [count], eps_abs)


def emit_photon_jobs(scene: Scene, seed: int, keys, counts, eps_abs: float) -> RayBatch:
    """The photons of several jobs at once, job after job, each exactly as
    `emit_photon_job` makes it (rng key keys[m], counts[m] photons); their
    `job` column holds the keys."""
    L = scene.lights
    keys = np.asarray(keys, np.uint64)
    counts = np.asarray(counts, np.int64)
    starts = np.zeros(len(counts) + 1, np.int64)
    np.cumsum(counts, out=starts[1:])
    o, d, f, st, light = emit.emit_photons(L.kind, L.p0, L.p1, L.p2, L.value, L.cone, L.power,
                                           L.cdf, np.uint64(seed), keys, starts, eps_abs,
                                           envmap.env_arrays(L), light_textures(L))
    # A photon path's pixel is -1 - its light: its first hit teaches the
    # light cache (`kernels.light_cache`) which light reaches there.
    return RayBatch(o, d, f, -1 - light, np.zeros(len(light), np.int32), st,
                    job=np.repeat(keys.astype(np.int64), counts))


def eye_ray_job(scene: Scene, seed: int, iteration: int, pixel_start: int, count: int) -> RayBatch:
    """Eye rays of pixels [pixel_start, pixel_start + count) of one iteration."""
    frame = scene.camera.frame()
    o, d, st = emit.generate_eye_rays(frame, int(scene.camera.width), np.uint64(seed),
                                      np.uint64(iteration), pixel_start, count)
    pixel = np.arange(pixel_start, pixel_start + count, dtype=np.int32)
    return RayBatch(o, d, np.ones((count, 3), np.float32), pixel, np.zeros(count, np.int32), st)


def photon_step(accel: Accelerator, surf: SurfaceData, batch: RayBatch,
                cull_box: np.ndarray, max_depth: int, deposit_from: int = 0, lights: tuple | None = None):
    """One bounce. Returns (deposits, continuing batch, end counts, culled)."""
    prim, _t, u, v = accel.intersect(batch.origin, batch.direction)
    return scatter_photons(surf, batch, prim, u, v, cull_box, max_depth, deposit_from, lights)


def scatter_photons(surf: SurfaceData, batch: RayBatch, prim, u, v,
                    cull_box: np.ndarray, max_depth: int, deposit_from: int = 0, lights: tuple | None = None):
    """The photon bounce at known hits (`prim` -1: escaped), for any
    aggregate: the whole scene or one chunk (`surf` indexes like `prim`).
    Photons deposit from their surface `deposit_from` on (0 or 1: see
    `RenderSettings.deposit_from`). With `lights` (`light_arrays`), the
    first hits teach its light cache."""
    if lights is not None:
        light_cache.learn_first_hits(lights[LEARN], batch.direction, batch.weight, batch.depth,
                                     batch.pixel, prim, u, v, surf)
    # float64: one compiled kernel whatever the caller's box (exact for float32)
    box = np.asarray(cull_box, np.float64)
    ends, culled, dep, nxt = paths.scatter_photons(
        (batch.direction, batch.weight, batch.depth, batch.rng, batch.job, batch.pixel),
        (prim, u, v), surf, surf.smooth_normals, surf.material_extras, box, max_depth, int(deposit_from),
        EPS_REL)
    no, nd, nf, st, depth, job, pixel = nxt
    return (PhotonDeposits(*dep), RayBatch(no, nd, nf, pixel, depth, st, job=job),
            ends, culled)


def eye_step(accel: Accelerator, surf: SurfaceData, batch: RayBatch, max_depth: int,
             lights: tuple | None = None, env: "Environment | None" = None):
    """One bounce of eye paths. Returns (hit points, emitted (pixel, rgb),
    continuing batch, end counts, shadow rays)."""
    prim, _t, u, v = accel.intersect(batch.origin, batch.direction)
    return advance_eye(surf, batch, prim, u, v, max_depth, lights, env)


def advance_eye(surf: SurfaceData, batch: RayBatch, prim, u, v, max_depth: int,
                lights: tuple | None = None, env: "Environment | None" = None):
    """The eye-path bounce at known hits, for any aggregate. With `lights`
    (`light_arrays`), each hit point also samples a light: its path goes
    on as a shadow ray, and ends (STORED) when that ray does. With `env`,
    paths that leave the scene see the environment."""
    kernel = paths.advance_eye_paths if len(batch) >= paths.SERIAL_BELOW else paths.advance_eye_paths_serial
    ends, (lit, rgb), (h, hpos, hn, hmat), (g, no, nd, nw, st) = kernel(
        (batch.direction, batch.weight, batch.depth, batch.rng), (prim, u, v), surf, surf.smooth_normals,
        surf.material_extras, max_depth, EPS_REL)
    weight = batch.weight[h]
    if len(surf.tex_info) and len(h):
        # A textured hit point carries its texel in its weight (`kernels.texture`).
        texture.fold_texels(surf, prim[h], hmat, u[h], v[h], weight)
    if len(surf.light_tex_info) and len(lit):
        texture.fold_emission(surf, prim[lit], u[lit], v[lit], rgb)     # a textured area light seen
    outgoing = -batch.direction[h]
    mapped = None
    if surf.shading_mapped and len(h):
        # Normal and bump maps: the hit point keeps the perturbed normal (`kernels.shading`).
        mapped = shading.perturb_hit_points(surf, prim[h], hmat, u[h], v[h], hn, outgoing)
    frames = None
    if surf.anisotropic:    # the tangent frames of anisotropic hit points (`kernels.anisotropic`)
        frames = anisotropic.hit_point_frames(surf, prim[h], hmat, u[h], v[h], hn)
    hits = HitPoints(hpos, hn, outgoing, weight, hmat, batch.pixel[h],
                     None if frames is None else frames.astype(np.float32))
    nxt = RayBatch(no, nd, nw, batch.pixel[g], batch.depth[g] + 1, st, job=batch.job[g])
    shadows = ShadowRays.empty()
    if lights is not None and len(hits):
        shadows = shadow_rays(surf, lights, hits, batch.rng[h], batch.job[h], mapped, frames)
        ends[STORED] -= len(shadows)
    seen = (batch.pixel[lit], rgb)
    if env is not None:
        seen = _concat_light(seen, escaped_light(env, batch.take(np.flatnonzero(prim == -1))))
    return hits, seen, nxt, ends, shadows


# -- infinite lights ----------------------------------------------------------------
class Environment(NamedTuple):
    """The environment light as the eye passes need it: the map's kernel
    arrays (`kernels.envmap.env_arrays`), and the probability that the
    light technique of glossy hit points (by power) picks it."""
    arrays: tuple
    p_select: float


def environment(lights: LightTable) -> Environment | None:
    """The scene's environment light, None if it has none."""
    rows = np.flatnonzero(lights.kind == LIGHT_ENV)
    if not len(rows) or not lights.power[rows[0]] > 0:
        return None
    return Environment(envmap.env_arrays(lights), float(lights.power[rows[0]] / lights.total_power))


def escaped_light(env: Environment | None, paths: RayBatch):
    """(pixel, rgb) that eye paths leaving the scene bring: their weight
    times the environment's radiance in their direction. Emission seen
    along an eye path always counts (it only passes specular surfaces),
    so the environment does too."""
    if env is None or not len(paths):
        return np.empty(0, np.int32), np.empty((0, 3), np.float32)
    return paths.pixel, envmap.escaped_radiance(env.arrays, paths.direction, paths.weight)


def _concat_light(a, b):
    if not len(b[0]):
        return a
    return np.concatenate([a[0], b[0]]), np.concatenate([a[1], b[1]])


def _infinite_arrays(lights: LightTable) -> tuple:
    """`kernels.direct`'s `infinite`: the cdf by power over the infinite
    lights, the share of light choices given to them (all when there are
    no others, half when there are), the environment's arrays."""
    inf = (lights.kind == LIGHT_DIRECTIONAL) | (lights.kind == LIGHT_ENV)
    power = np.where(inf, lights.power, 0.0)
    total = power.sum()
    cdf = np.cumsum(power) / total if total > 0 else np.zeros_like(power)
    if total > 0:
        cdf[np.flatnonzero(inf)[-1]:] = 1.0
    share = 0.0 if not total > 0 else 1.0 if np.all(inf | ~(lights.power > 0)) else 0.5
    return (cdf, np.array([share]), *envmap.env_arrays(lights))


def _infinite_or_none(infinite: tuple) -> tuple | None:
    """`infinite`, or None in a scene without infinite lights (no share of
    the choices): `kernels.direct` is then compiled without their branches,
    as the bounces are without the extras (no speed measured from it alone)."""
    return infinite if infinite[1][0] > 0.0 else None


# -- direct light -----------------------------------------------------------------
LIGHT_TEXTURE = 14    # light_arrays()[14:19]: the lights' textures (`light_textures`)
LIGHT_CACHE = 19      # light_arrays()[LIGHT_CACHE]: the light cache's arrays the eye passes read
LEARN = 20            # light_arrays()[LEARN]: those the photons teach (the same, or the live ones)
INFINITE = 21         # light_arrays()[INFINITE]: the infinite lights (`_infinite_arrays`)


def light_textures(lights: LightTable) -> tuple:
    """The textured lights' arrays as the kernels take them: (texture id
    per light, tex_info, tex_uv, tex_texels, tri_uv; `LightTable`)."""
    return (lights.texture, lights.tex_info, lights.tex_uv, lights.tex_texels, lights.tri_uv)


def light_arrays(lights: LightTable, cache: LightCache | None = None) -> tuple:
    """The light table as the tuple the direct-light kernel reads: its rows,
    its light tree's arrays (flat: numba's parallel loops refuse a tuple
    nested in their arguments), the arrays of the light cache that the
    photons' first hits teach (`kernels.light_cache`; none: the tree alone)
    and those of the infinite lights."""
    L = lights
    cache = cache if cache is not None else LightCache.empty()
    return (L.kind, L.p0, L.p1, L.p2, L.value, L.cone, L.power, L.cdf, *build_light_tree(L),
            *light_textures(L), cache.read, cache.arrays(), _infinite_arrays(L))


def freeze_light_cache(lights: tuple | None) -> None:
    """Start an eye iteration: its choices read the table as the photons
    have taught it so far (`LightCache` with `frozen`)."""
    if lights is not None and lights[LIGHT_CACHE][0] is not lights[LEARN][0]:
        for read, live in zip(lights[LIGHT_CACHE], lights[LEARN]):
            np.copyto(read, live)


def shadow_rays(surf: SurfaceData, lights: tuple, hits: HitPoints, states, jobs,
                mapped: tuple | None = None, frames: np.ndarray | None = None) -> ShadowRays:
    """The direct-light ray of each hit point (`kernels.direct`: a shadow
    ray to a light sample, or on glossy surfaces under triangle lights a
    BSDF-sampled one, by one-sample MIS); hit points whose sample cannot
    contribute get none. `mapped`: (geometric normals, a2) of hit points
    whose normal a normal or bump map perturbed (`kernels.shading`);
    `frames` those of anisotropic hit points (`kernels.anisotropic`)."""
    frames = np.zeros((0, 5)) if frames is None else frames
    mis = bool(np.any((lights[0] == LIGHT_TRIANGLE) | ((lights[0] == LIGHT_ENV) & (lights[6] > 0))))
    kernel = direct.sample_direct if len(hits) >= paths.SERIAL_BELOW else direct.sample_direct_serial
    rows, o, d, tmax, rgb, pdf = kernel(
        (hits.position, hits.normal, hits.outgoing, hits.weight, hits.material, frames),
        np.ascontiguousarray(states), surf, surf.material_extras, lights[:LIGHT_CACHE], lights[LIGHT_CACHE],
        _infinite_or_none(lights[INFINITE]), mis, EPS_REL)
    if mapped is not None:
        rgb *= shading.terminator_factor(d, mapped[0][rows], mapped[1][rows])[:, None].astype(np.float32)
    return ShadowRays(o, d, rgb, tmax, pdf, hits.pixel[rows], job=np.asarray(jobs)[rows])


def shadow_results(shadows: ShadowRays, prim, t, surf: SurfaceData, total_power: float, ended=None,
                   env: Environment | None = None, uv=None):
    """(pixel, rgb) that the ended rays among `shadows` bring, given their
    first hits in [0, tmax] (`prim` -1: none): a shadow ray with no hit
    reached its light; a BSDF-sampled one brings what its hit emits, or,
    with `env`, what the environment sends if it left the scene.
    `ended` (bool) limits it to rays that end here (not leaving a chunk);
    `uv` the hits' barycentrics (u, v), which a textured area light needs."""
    ended = np.ones(len(shadows), bool) if ended is None else ended
    lit = ended & (shadows.pdf == 0) & (prim < 0)
    found = np.flatnonzero(ended & (shadows.pdf > 0) & (prim >= 0))
    rgb = direct.emitter_radiance(shadows.direction[found], shadows.radiance[found], shadows.pdf[found],
                                  prim[found], t[found], surf, float(total_power))
    if len(surf.light_tex_info) and len(found):
        texture.fold_emission(surf, prim[found], uv[0][found], uv[1][found], rgb)
    out = (np.concatenate([shadows.pixel[lit], shadows.pixel[found]]),
           np.concatenate([shadows.radiance[lit], rgb]))
    if env is not None:
        away = np.flatnonzero(ended & (shadows.pdf > 0) & (prim < 0))
        sky = envmap.escaped_mis_radiance(env.arrays, shadows.direction[away], shadows.radiance[away],
                                          shadows.pdf[away], direct.C_LIGHT, env.p_select)
        out = _concat_light(out, (shadows.pixel[away], sky))
    return out


def trace_shadows(accel: Accelerator, surf: SurfaceData, lights: tuple, shadows: ShadowRays,
                  env: Environment | None = None):
    """Direct-light rays against one aggregate holding the whole scene.
    Returns ((pixel, rgb) of the light they found, end counts)."""
    ends = np.zeros(END_KINDS, np.int64)
    ends[STORED] = len(shadows)
    if not len(shadows):
        return (np.empty(0, np.int32), np.empty((0, 3), np.float32)), ends
    prim, t, u, v = accel.intersect(shadows.origin, shadows.direction, shadows.tmax)
    return shadow_results(shadows, prim, t, surf, lights[6].sum(), env=env, uv=(u, v)), ends


def trace_photons(accel, surf, batch, cull_box, max_depth, deposit_from: int = 0, lights: tuple | None = None):
    """Follow one photon batch until every path ends (one aggregate)."""
    return trace_photon_jobs(accel, surf, [batch], cull_box, max_depth, min_batch=1,
                             deposit_from=deposit_from, lights=lights)


def trace_photon_jobs(accel, surf, jobs, cull_box, max_depth, min_batch: int = 32_768,
                      on_batch=None, deposit_from: int = 0, lights: tuple | None = None):
    """Trace an iterable of photon jobs (RayBatches) as one stream: new jobs
    join the continuing paths whenever fewer than `min_batch` are in flight
    (client batching, §4.3), so Russian roulette's thinning tail never
    leaves Embree and the kernels with tiny batches. Paths draw from their
    own random streams, so the photons traced do not depend on the batching.
    `on_batch(batch)` sees every traced batch (benchmarks replay them);
    with `lights`, first hits teach its light cache."""
    jobs = iter(jobs)
    deposits, ends, culled = [], np.zeros(END_KINDS, np.int64), 0
    active, exhausted = RayBatch.empty(), False
    while True:
        pending = [active]
        size = len(active)
        while not exhausted and size < min_batch:
            job = next(jobs, None)
            if job is None:
                exhausted = True
            else:
                pending.append(job)
                size += len(job)
        active = RayBatch.concat(pending) if len(pending) > 1 else active
        if not len(active):
            break
        if on_batch is not None:
            on_batch(active)
        dep, active, e, c = photon_step(accel, surf, active, cull_box, max_depth, deposit_from, lights)
        deposits.append(dep)
        ends += e
        culled += c
    ends[0] = 0
    return PhotonDeposits.concat(deposits), ends, culled


def trace_eye(accel, surf, batch, max_depth, lights: tuple | None = None, env: Environment | None = None):
    """Follow eye paths until each stores a hit point or ends; with
    `lights`, trace each hit point's shadow ray too; with `env`, paths
    leaving the scene see it. Returns (hit points, (pixel, rgb) of light
    seen directly and, with `lights`, direct light at hit points, end
    counts)."""
    hits, pix, rgb, shadows, ends = [], [], [], [], np.zeros(END_KINDS, np.int64)
    while len(batch):
        h, (p, e), batch, c, s = eye_step(accel, surf, batch, max_depth, lights, env)
        hits.append(h)
        pix.append(p)
        rgb.append(e)
        shadows.append(s)
        ends += c
    (p, e), c = trace_shadows(accel, surf, lights, ShadowRays.concat(shadows), env)
    pix.append(p)
    rgb.append(e)
    ends += c
    ends[0] = 0
    return HitPoints.concat(hits), (np.concatenate(pix), np.concatenate(rgb)), ends
