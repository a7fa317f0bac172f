"""The limit reference for what the camera sees in a perfect mirror (issue 5).

Where the camera sees a mirror that shows a floor lit by a point light's
caustic (specular-diffuse-specular paths), no independent method converges:
a path tracer cannot find the point light behind the mirror and the floor,
and a light tracer cannot connect a floor vertex to the camera through the
mirror. But a perfect mirror only relays light: the radiance of an eye ray
that meets mirrors and then the floor at p is

    L = rho_1 * rho_2 * ... * L_floor(p)       (per RGB channel)

and because the floor is Lambertian, L_floor(p) is the same in every
direction, so it can be rendered where a light tracer does converge: the
floor seen from straight above, by Mitsuba's `ptracer`. This module builds
that top-down image (cached like the other references), follows each
pixel's jittered eye rays (our camera's ray generation and box filter)
through the scene's mirrors with the law of reflection, and looks the floor
radiance up where they land. The geometry is the scene's; no radiance of
ours enters, so our renders are never their own reference.

Assumptions, checked where they can be: the floor is the scene's only
diffuse material, flat, horizontal and facing up; mirrors are the only
other surfaces eye rays meet (a ray meeting anything else makes its pixel
NaN: the limit does not cover it). An escaping ray carries 0: our scenes
have no environment light, nor do their Mitsuba exports. A point light
cannot be hit. The floor image counts light paths up to the reference
depth (10 bounces), the mirror adds one: a difference far below the noise.
"""
from __future__ import annotations

import dataclasses
import math

import numpy as np

from dosppm_core.accel import Accelerator
from dosppm_core.scene.model import Camera, DIFFUSE, MIRROR, Scene
from dosppm_core.trace import eye_ray_job
from harness.reference import SAFE_VARIANT, cached_reference

# The top-down camera stands this far above the floor, so the mirror ring
# (a wall seen edge-on) hides a strip of floor far narrower than a texel.
TOP_DOWN_DISTANCE_MM = 1e5
FLOOR, ESCAPED, ABSORBED, UNCOVERED = 0, 1, 2, 3


@dataclasses.dataclass(frozen=True)
class LimitSettings:
    """How the limit image is made. `max_depth` bounds the bounces of a
    whole light path (floor and mirrors), as the references' depth does:
    the floor image holds paths of up to max_depth - 1 bounces and an eye
    ray may meet up to max_depth - 1 mirrors (exact for one mirror; deeper
    chains may hold a path a few bounces too long, which carries nothing
    measurable here)."""
    rays_per_pixel: int = 1024
    floor_resolution: int = 1024  # texels along each side of the floor image
    floor_spp: int = 256          # ptracer samples per texel (268M light paths)
    max_depth: int = 10           # the references' and our renderer's default
    seed: int = 777               # eye-ray jitter, unrelated to any render's seed
    floor_seed: int = 0


@dataclasses.dataclass
class MirrorPaths:
    """Where a batch of eye rays ends after its mirror bounces."""
    point: np.ndarray             # (n, 3) float64 floor point (valid where end == FLOOR)
    weight: np.ndarray            # (n, 3) product of the mirror reflectances met
    end: np.ndarray               # (n,) FLOOR, ESCAPED, ABSORBED or UNCOVERED
    bounces: np.ndarray           # (n,) mirror bounces made


def floor_height(scene: Scene) -> tuple[int, float]:
    """(material id, y) of the floor: the scene's only diffuse material,
    every triangle of it horizontal at one height and facing +y."""
    diffuse = np.flatnonzero(scene.materials.kind == DIFFUSE)
    if len(diffuse) != 1:
        raise ValueError(f"{scene.name}: the mirror limit needs exactly one diffuse material "
                         f"(the floor), found {len(diffuse)}")
    mid = int(diffuse[0])
    tri = scene.triangles[scene.tri_material == mid]
    y = scene.vertices[tri][..., 1].astype(np.float64)
    normal = _normals(scene.vertices, tri)
    if np.ptp(y) > 1e-6 * scene.diagonal() or np.any(normal[:, 1] < 1.0 - 1e-9):
        raise ValueError(f"{scene.name}: the mirror limit needs a flat floor facing +y")
    return mid, float(y.mean())


def _normals(vertices: np.ndarray, tri: np.ndarray) -> np.ndarray:
    v = vertices.astype(np.float64)[tri]
    n = np.cross(v[:, 1] - v[:, 0], v[:, 2] - v[:, 0])
    return n / np.linalg.norm(n, axis=1)[:, None]


def trace_mirror_paths(scene: Scene, accel, origin: np.ndarray, direction: np.ndarray,
                       floor_material: int, max_bounces: int) -> MirrorPaths:
    """Follow rays through perfect mirrors (law of reflection, the
    material's reflectance as a tint and no Fresnel term, as our BSDF and
    Mitsuba's `conductor` with material "none") until they meet the floor."""
    n = len(origin)
    o, d = origin.astype(np.float64), direction.astype(np.float64)
    out = MirrorPaths(np.zeros((n, 3)), np.ones((n, 3)), np.full(n, ESCAPED, np.int8),
                      np.zeros(n, np.int32))
    live = np.arange(n)
    eps = scene.spawn_epsilon()
    for bounce in range(max_bounces + 1):
        prim, t, _u, _v = accel.intersect(o, d)
        hit = prim >= 0
        out.end[live[~hit]] = ESCAPED
        live, o, d, prim, t = live[hit], o[hit], d[hit], prim[hit], t[hit].astype(np.float64)
        p = o + t[:, None] * d
        mat = scene.tri_material[prim]
        on_floor = mat == floor_material
        out.point[live[on_floor]] = p[on_floor]
        out.end[live[on_floor]] = FLOOR
        kind = scene.materials.kind[mat]
        out.end[live[(kind != MIRROR) & ~on_floor]] = UNCOVERED
        keep = (kind == MIRROR) & ~on_floor
        if bounce == max_bounces:
            out.end[live[keep]] = ABSORBED        # as deep as our eye paths go
            break
        live, o, d = _reflect(scene, out, live[keep], p[keep], d[keep], prim[keep], eps)
        if not len(live):
            break
    return out


def _reflect(scene: Scene, out: MirrorPaths, live, p, d, prim, eps: float):
    """The law of reflection at mirror hits: (rays still live, new origins,
    new directions); the reflectance tints the path's weight."""
    mat = scene.tri_material[prim]
    normal = _normals(scene.vertices, scene.triangles[prim])
    cos = np.einsum("ij,ij->i", normal, d)
    back = (cos > 0) & ~scene.materials.two_sided[mat]
    out.end[live[back]] = ABSORBED                # the black back of a one-sided mirror
    front = ~back
    live, p, d, normal, cos, mat = (x[front] for x in (live, p, d, normal, cos, mat))
    d = d - 2.0 * cos[:, None] * normal
    out.weight[live] *= scene.materials.reflectance[mat]
    out.bounces[live] += 1
    # Leave the facet on the side the reflected ray goes to.
    o = p + eps * np.sign(np.einsum("ij,ij->i", normal, d))[:, None] * normal
    return live, o, d


# -- the floor seen from above --------------------------------------------------

def top_down_camera(points: np.ndarray, floor_y: float, resolution: int) -> Camera:
    """A camera high above the floor looking straight down, its square view
    just covering `points` (x, z) with a margin of two texels."""
    lo, hi = points[:, [0, 2]].min(0), points[:, [0, 2]].max(0)
    centre = (lo + hi) / 2.0
    half = float(np.max(hi - lo)) / 2.0 * (1.0 + 4.0 / resolution) + 1e-3
    return Camera(position=(float(centre[0]), floor_y + TOP_DOWN_DISTANCE_MM, float(centre[1])),
                  look_at=(float(centre[0]), floor_y, float(centre[1])), up=(0.0, 0.0, 1.0),
                  fov_deg=2.0 * math.degrees(math.atan(half / TOP_DOWN_DISTANCE_MM)),
                  width=resolution, height=resolution)


def floor_image_coordinates(camera: Camera, points: np.ndarray) -> np.ndarray:
    """(n, 2) continuous (column, row) of floor points in `camera`'s image:
    the inverse of our eye-ray generation (`kernels.emit.generate_eye_rays`),
    which Mitsuba's perspective sensor matches; texel (c, r) spans
    [c, c + 1) x [r, r + 1)."""
    frame = camera.frame()
    pos, right, up, fwd = frame[0], frame[1], frame[2], frame[3]
    tan_x, tan_y = frame[4, 0], frame[4, 1]
    v = points - pos
    along = v @ fwd
    sx, sy = (v @ right) / along / tan_x, (v @ up) / along / tan_y
    return np.stack([(sx + 1.0) * camera.width / 2.0, (1.0 - sy) * camera.height / 2.0], 1)


def texel_centres(camera: Camera, floor_y: float, cr: np.ndarray) -> np.ndarray:
    """(n, 3) floor points at the centres of texels `cr` (n, 2) (column, row)."""
    frame = camera.frame()
    pos, right, up, fwd = frame[0], frame[1], frame[2], frame[3]
    sx = ((cr[:, 0] + 0.5) / camera.width * 2.0 - 1.0) * frame[4, 0]
    sy = (1.0 - (cr[:, 1] + 0.5) / camera.height * 2.0) * frame[4, 1]
    d = fwd + sx[:, None] * right + sy[:, None] * up
    return pos + d * ((floor_y - pos[1]) / d[:, 1])[:, None]


def texel_mm(camera: Camera) -> float:
    return 2.0 * TOP_DOWN_DISTANCE_MM * math.tan(math.radians(camera.fov_deg) / 2.0) / camera.width


def clean_texels(accel, camera: Camera, floor_y: float, lift_mm: float) -> np.ndarray:
    """(H, W) bool: texels whose footprint (grown by half) no wall crosses.
    A texel on a mirror's foot averages floor from both sides of it, which
    differ (light and shadow), so a lookup must not use it. Any straight
    wall crossing a square crosses one of its half-diagonals, so rays from
    the centre to the four corners find it."""
    rows, cols = np.mgrid[0:camera.height, 0:camera.width]
    centre = texel_centres(camera, floor_y, np.stack([cols.ravel(), rows.ravel()], 1))
    clean = np.ones(len(centre), bool)
    for dx, dz in ((1, 1), (1, -1), (-1, 1), (-1, -1)):
        step = 0.75 * texel_mm(camera) * np.array([dx, 0.0, dz])
        clean &= ~_blocked(accel, centre, step, lift_mm)
    return clean.reshape(camera.height, camera.width)


def _blocked(accel, start: np.ndarray, step: np.ndarray, lift_mm: float) -> np.ndarray:
    """Whether anything stands on the floor between `start` and
    `start + step`, seen just above the floor."""
    o = start + np.array([0.0, lift_mm, 0.0])
    step = np.broadcast_to(step, o.shape)
    length = np.linalg.norm(step, axis=1)
    prim, t, _u, _v = accel.intersect(o, step / length[:, None], tmax=length)
    return (prim >= 0) & (t < length)


def look_up_floor(floor_image: np.ndarray, clean: np.ndarray, camera: Camera, accel,
                  points: np.ndarray, floor_y: float, lift_mm: float):
    """((n, 3) floor radiance at `points`, (n,) found): bilinear over the
    four nearest texel centres that are clean and on the same side of any
    wall as the point; a point with none (at a wall's foot) takes the
    nearest such texel of the 4x4 around it; `found` is False where even
    that fails (the radiance is then 0)."""
    uv = floor_image_coordinates(camera, points) - 0.5
    base = np.floor(uv).astype(np.int64)
    frac = uv - base
    total, norm = np.zeros((len(points), 3)), np.zeros(len(points))
    for dc, dr in ((0, 0), (1, 0), (0, 1), (1, 1)):
        w = (frac[:, 0] if dc else 1.0 - frac[:, 0]) * (frac[:, 1] if dr else 1.0 - frac[:, 1])
        value, ok = _texel(floor_image, clean, camera, accel, points, base + (dc, dr),
                           floor_y, lift_mm)
        total += (w * ok)[:, None] * value
        norm += w * ok
    out = total / np.maximum(norm, 1e-300)[:, None]
    lost = norm <= 1e-12
    found = ~lost
    if np.any(lost):
        out[lost], found[lost] = _nearest_usable(floor_image, clean, camera, accel, points[lost],
                                                 base[lost], uv[lost], floor_y, lift_mm)
    return out, found


def _texel(floor_image, clean, camera, accel, points, cr, floor_y, lift_mm):
    """(value, usable) of texels `cr` (n, 2) seen from `points`."""
    h, w = clean.shape
    inside = (cr[:, 0] >= 0) & (cr[:, 0] < w) & (cr[:, 1] >= 0) & (cr[:, 1] < h)
    c, r = np.clip(cr[:, 0], 0, w - 1), np.clip(cr[:, 1], 0, h - 1)
    ok = inside & clean[r, c]
    centre = texel_centres(camera, floor_y, np.stack([c, r], 1))
    step = centre - points
    step[:, 1] = 0.0
    near = np.linalg.norm(step, axis=1) < 1e-9
    seen = near.copy()
    far = ~near
    seen[far] = ~_blocked(accel, points[far], step[far], lift_mm)
    return floor_image[r, c].astype(np.float64), ok & seen


def _nearest_usable(floor_image, clean, camera, accel, points, base, uv, floor_y, lift_mm):
    best, value = np.full(len(points), np.inf), np.zeros((len(points), 3))
    for dc in range(-1, 3):
        for dr in range(-1, 3):
            cr = base + (dc, dr)
            v, ok = _texel(floor_image, clean, camera, accel, points, cr, floor_y, lift_mm)
            dist = np.sum((cr - uv) ** 2, axis=1)
            better = ok & (dist < best)
            best[better], value[better] = dist[better], v[better]
    return value, np.isfinite(best)


# -- the limit image ------------------------------------------------------------

@dataclasses.dataclass
class MirrorLimit:
    """The limit image and what it rests on."""
    image: np.ndarray             # (H, W, 3); NaN outside the pixels asked for
    floor_image: np.ndarray       # the top-down ptracer render of the floor
    floor_camera: Camera
    end_share: dict               # 'floor', 'escaped', 'absorbed', 'uncovered' -> share of rays
    mirror_share: float           # share of rays whose first surface is a mirror
    unusable_share: float         # share of floor rays no clean texel could serve


def mirror_limit(scene: Scene, cache_dir: str, pixels: np.ndarray | None = None,
                 settings: LimitSettings = LimitSettings(), variant: str = SAFE_VARIANT) -> MirrorLimit:
    """The limit image over `pixels` ((H, W) bool, None for all): each
    pixel the mean over its jittered eye rays of the mirror reflectances
    met times the floor radiance where the ray lands. `variant` is the
    Mitsuba variant of the floor image (see `reference`)."""
    floor_material, floor_y = floor_height(scene)
    accel = Accelerator(scene.vertices, scene.triangles)
    try:
        s = settings
        pixel, origin, direction = _eye_rays(scene, pixels, s.rays_per_pixel, s.seed)
        ends = trace_mirror_paths(scene, accel, origin, direction, floor_material, s.max_depth - 1)
        on_floor = ends.end == FLOOR
        camera = top_down_camera(ends.point[on_floor], floor_y, s.floor_resolution)
        top = dataclasses.replace(scene, camera=camera, name=f"{scene.name}-floor")
        floor_image = cached_reference(top, s.floor_spp, cache_dir, max_depth=s.max_depth - 1,
                                       integrator="ptracer", seed=s.floor_seed, variant=variant)
        lift = 1e-4 * scene.diagonal()
        clean = clean_texels(accel, camera, floor_y, lift)
        radiance = np.zeros((len(pixel), 3))
        floor_radiance, found = look_up_floor(floor_image, clean, camera, accel,
                                              ends.point[on_floor], floor_y, lift)
        radiance[on_floor] = ends.weight[on_floor] * floor_radiance
    finally:
        accel.close()
    radiance[ends.end == UNCOVERED] = np.nan      # the limit says nothing there
    image = _pixel_means(scene, pixel, radiance, pixels)
    names = {FLOOR: "floor", ESCAPED: "escaped", ABSORBED: "absorbed", UNCOVERED: "uncovered"}
    return MirrorLimit(image, floor_image, camera,
                       {name: float(np.mean(ends.end == k)) for k, name in names.items()},
                       float(np.mean(ends.bounces > 0)),
                       float(np.mean(~found)) if len(found) else 0.0)


def _eye_rays(scene: Scene, pixels, rays_per_pixel: int, seed: int):
    """(pixel, origin, direction) of the jittered eye rays of `pixels`: our
    renderer's ray generation and box filter (`trace.eye_ray_job`)."""
    w, h = int(scene.camera.width), int(scene.camera.height)
    chosen = np.ones(w * h, bool) if pixels is None else np.asarray(pixels, bool).ravel()
    parts = []
    for k in range(rays_per_pixel):
        rays = eye_ray_job(scene, seed, k, 0, w * h)
        parts.append((rays.pixel[chosen], rays.origin[chosen], rays.direction[chosen]))
    return tuple(np.concatenate([p[i] for p in parts]) for i in range(3))


def _pixel_means(scene: Scene, pixel: np.ndarray, radiance: np.ndarray, pixels) -> np.ndarray:
    w, h = int(scene.camera.width), int(scene.camera.height)
    count = np.bincount(pixel, minlength=w * h).astype(np.float64)
    image = np.stack([np.bincount(pixel, radiance[:, c], minlength=w * h) for c in range(3)], 1)
    with np.errstate(invalid="ignore", divide="ignore"):
        image = image / count[:, None]
    image[count == 0] = np.nan
    return image.reshape(h, w, 3).astype(np.float32)
