"""The light table: every light of a scene as one row, for power-proportional
selection, and how `SceneBuilder` (and a streamed soup's writer) builds it.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from dosppm_core.scene.light_textures import textured_flux
from dosppm_core.scene.textures import TextureTable

# Light kinds, as stored in `LightTable.kind`. Directional and environment
# lights are infinitely far: their photons leave a disc outside the scene's
# bounding sphere, and their shadow rays run to past that sphere.
LIGHT_TRIANGLE, LIGHT_POINT, LIGHT_SPOT, LIGHT_DIRECTIONAL, LIGHT_ENV, LIGHT_PROJECTOR = 0, 1, 2, 3, 4, 5
# The bounding sphere of the infinite lights' discs: the scene box's, this
# much larger (Mitsuba enlarges its own by 1 + RayEpsilon).
SPHERE_MARGIN = 1e-3


@dataclass
class LightTable:
    """Every light as one row, for power-proportional selection.

    Triangle lights store their vertices in p0..p2 and radiance in `value`;
    point and spot lights store position in p0, intensity (W/sr) in `value`,
    and spots their unit axis in p1 and (cos cutoff, cos beam, cutoff rad,
    beam rad) in `cone`; a projector (Mitsuba's, untextured) its unit
    axis in p1, its image's x axis in p2, the irradiance its image plane at
    distance 1 has in `value` (its intensity is pi value / cos^3) and the
    half extents (tan x, tan y) of its frustum in cone[0:2]. The infinite
    lights store the scene's bounding sphere, centre in p1 and radius in
    cone[0]: a directional light its unit
    direction of travel in p0 and irradiance (W/m^2) in `value`, the
    environment (at most one row) its mean radiance in `value`, its texels
    in `env_texels` (Mitsuba's layout: rows from theta 0 to pi, the first
    column repeated at the end; scale applied) and its rotation in
    `env_to_world`. `power` is the emitted flux per row (RGB mean; pi R^2
    times the irradiance, or the integral of the radiance over the sphere,
    for the infinite ones), and `cdf` its normalised running sum.

    A textured spot or projector (`scene.light_textures`) keeps its image's
    x axis in p2 and names its texture in `texture` (-1: none), an index
    into the lights' own texture arrays `tex_info`, `tex_uv`, `tex_texels`
    (a `TextureTable`'s, apart from the materials' so that every chunk has
    them); `value` stays the untextured intensity or irradiance, which the
    kernels multiply by the texel of the direction. A triangle of a
    textured area light names its material's emission texture there too,
    with its corners' texture coordinates in `tri_uv` (u0, v0, u1, v1, u2,
    v2), and `value` its material's emission (the texture's mean).
    """
    kind: np.ndarray     # int32 (L,)
    p0: np.ndarray       # float64 (L, 3)
    p1: np.ndarray
    p2: np.ndarray
    value: np.ndarray    # float64 (L, 3)
    cone: np.ndarray     # float64 (L, 4)
    power: np.ndarray    # float64 (L,)
    cdf: np.ndarray      # float64 (L,)
    # A black 2x2 map when the scene has no environment: the kernels' types stay one.
    env_texels: np.ndarray = field(default_factory=lambda: np.zeros((2, 2, 3), np.float32))
    env_to_world: np.ndarray = field(default_factory=lambda: np.eye(3))
    texture: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int32))     # int32 (L,)
    tex_info: np.ndarray = field(default_factory=lambda: np.zeros((0, 6), np.int32))
    tex_uv: np.ndarray = field(default_factory=lambda: np.zeros((0, 6), np.float64))
    tex_texels: np.ndarray = field(default_factory=lambda: np.zeros((0, 3), np.float32))
    tri_uv: np.ndarray = field(default_factory=lambda: np.zeros((0, 6), np.float64))

    def __post_init__(self):
        if self.texture.shape != self.kind.shape:       # a table without textured lights
            self.texture = np.full(self.kind.shape, -1, np.int32)
        if self.tri_uv.shape != (len(self.kind), 6):
            self.tri_uv = np.zeros((len(self.kind), 6), np.float64)

    @property
    def total_power(self) -> float:
        return float(self.power.sum())

    @property
    def has_environment(self) -> bool:
        return bool(np.any(self.kind == LIGHT_ENV))

    def env_distribution(self):
        """The environment's sampling tables (`scene.envmap.distribution`),
        built once."""
        cached = self.__dict__.get("_env_distribution")
        if cached is None or cached[0] is not self.env_texels:
            from dosppm_core.scene.envmap import distribution
            cached = (self.env_texels, distribution(self.env_texels))
            self.__dict__["_env_distribution"] = cached
        return cached[1]

    def wire_fields(self) -> dict:
        """The fields (no caches): what the wire and content keys carry."""
        return {k: v for k, v in vars(self).items() if not k.startswith("_")}


def bounding_radius(lo, hi) -> float:
    """The radius of the infinite lights' sphere around box (lo, hi)."""
    r = 0.5 * float(np.linalg.norm(np.asarray(hi, np.float64) - lo))
    return max(r * (1 + SPHERE_MARGIN), 1e-6)


def light_table(p0, p1, p2, radiance, delta_lights=(), directional=(), environment=None,
                sphere=None, emission_textures=None) -> LightTable:
    """The light table of emissive triangles and point/spot lights.

    p0, p1, p2: (n, 3) corners of the emissive triangles, each emitting
    `radiance` (n, 3) on its counter-clockwise front; `delta_lights`:
    (kind, position, axis, intensity, cone[, x axis]) tuples as `SceneBuilder`
    collects them. Triangles come first, in the order given, so a writer
    that streams its triangles (a generated soup) can build the same table
    as `SceneBuilder` from its emissive triangles alone. `directional`:
    (unit direction, irradiance) pairs; `environment`: (texels, rotation)
    or None; both need `sphere`, (centre, radius) around the scene.
    `emission_textures`: (texture id per triangle, (n, 6) corner uvs, the
    textures those ids index) of textured area lights, or None.
    """
    p0, p1, p2, radiance = (np.asarray(a, np.float64).reshape(-1, 3) for a in (p0, p1, p2, radiance))
    n = len(p0)
    area = 0.5 * np.linalg.norm(np.cross(p1 - p0, p2 - p0), axis=1)
    rows_kind = [np.full(n, LIGHT_TRIANGLE, np.int32)]
    rows = [p0, p1, p2, radiance, np.zeros((n, 4))]
    # One-sided Lambertian emitter: flux = pi * L * area per channel.
    power = [math.pi * area * radiance.mean(axis=1)]
    textures, texture_of, tri_uv = [], [np.full(n, -1, np.int32)], np.zeros((n, 6))
    if emission_textures is not None:
        texture_of[0] = np.asarray(emission_textures[0], np.int32).reshape(n)
        tri_uv = np.asarray(emission_textures[1], np.float64).reshape(n, 6)
        textures = list(emission_textures[2])
    for kind, pos, axis, val, cone, *rest in delta_lights:
        rows_kind.append(np.array([kind], np.int32))
        for i, x in enumerate((pos, axis, rest[0] if rest else np.zeros(3), val, cone)):
            rows[i] = np.concatenate([rows[i], np.asarray(x, np.float64)[None]])
        if len(rest) > 1:           # textured: its flux integrates the texels it sends out
            texture_of.append(np.array([len(textures)], np.int32))
            textures.append(rest[1])
            flux = textured_flux(kind == LIGHT_PROJECTOR, np.asarray(cone), rest[1])
            power.append(np.array([np.mean(np.asarray(val) * flux)]))
            continue
        texture_of.append(np.array([-1], np.int32))
        power.append(np.array([np.mean(val) * _delta_solid_angle(kind, np.asarray(cone))]))
    env = _infinite_rows(directional, environment, sphere, rows_kind, rows, power)
    texture_of.append(np.full(len(power) - len(texture_of), -1, np.int32))
    power = np.concatenate(power)
    total = power.sum()
    cdf = np.cumsum(power) / total if total > 0 else np.zeros_like(power)
    if cdf.size:
        cdf[-1] = 1.0
    tri_uv = np.concatenate([tri_uv, np.zeros((len(power) - n, 6))])
    table = LightTable(np.concatenate(rows_kind), rows[0], rows[1], rows[2], rows[3],
                       rows[4], power, cdf, texture=np.concatenate(texture_of), tri_uv=tri_uv)
    if textures:
        lights_textures = TextureTable.from_textures(textures)
        table.tex_info, table.tex_uv, table.tex_texels = (lights_textures.info, lights_textures.uv_map,
                                                          lights_textures.texels)
    if env is not None:
        table.env_texels, table.env_to_world = env
    return table


def _infinite_rows(directional, environment, sphere, rows_kind, rows, power):
    """Append the directional and environment rows (`light_table`);
    returns the environment's (texels, rotation) or None. Their flux is
    what crosses the sphere's disc: pi R^2 E, or pi R^2 times the integral
    of the radiance over directions."""
    if not directional and environment is None:
        return None
    centre, radius = np.asarray(sphere[0], np.float64), float(sphere[1])
    disc = math.pi * radius * radius
    cone = np.array([radius, 0.0, 0.0, 0.0])
    entries = [(LIGHT_DIRECTIONAL, d, e, disc * np.mean(e)) for d, e in directional]
    if environment is not None:
        from dosppm_core.scene.envmap import radiance_integral
        integral = radiance_integral(environment[0])
        entries.append((LIGHT_ENV, np.zeros(3), integral / (4 * math.pi), disc * np.mean(integral)))
    for kind, direction, value, flux in entries:
        rows_kind.append(np.array([kind], np.int32))
        for i, x in enumerate((direction, centre, np.zeros(3), value, cone)):
            rows[i] = np.concatenate([rows[i], np.asarray(x, np.float64)[None]])
        power.append(np.array([flux]))
    return environment


def _delta_solid_angle(kind: int, cone: np.ndarray) -> float:
    """Integral of the angular falloff over the sphere: 4 pi for a point
    light; for a spot, the full cone to the beam plus the linear ramp."""
    if kind == LIGHT_POINT:
        return 4 * math.pi
    if kind == LIGHT_PROJECTOR:       # pi E over the image plane at distance 1
        return math.pi * 4 * cone[0] * cone[1]
    cutoff, beam = cone[2], cone[3]
    full = 2 * math.pi * (1 - math.cos(beam))
    # Ramp: integral of 2 pi sin(t) (cutoff - t) / (cutoff - beam) dt over
    # [beam, cutoff], by parts: ((cutoff - beam) cos(beam) - (sin(cutoff) - sin(beam))).
    ramp = 0.0
    if cutoff > beam:
        w = cutoff - beam
        ramp = 2 * math.pi * (w * math.cos(beam) - (math.sin(cutoff) - math.sin(beam))) / w
    return full + ramp
