"""Render settings and progress records: one home for every default.

The same `RenderSettings` reach every mode: single-process SPPM and OSPPM
read them directly, the DOSPPM server hands them to each tracer at
registration. The command line and the service configuration take their
defaults from here.
"""
from __future__ import annotations

import dataclasses
import os
from dataclasses import dataclass, field


DIRECT_MODES = ("nee", "photons")
LIGHT_CACHE_BYTES = 32 << 20   # RenderSettings.light_cache
# Photons per iteration when none are given: per pixel of the image, so an
# eye pass (hit points and their shadow rays, which carry the direct light)
# comes as often, relative to the photons, at any image size. Measured at
# equal time: the Cornell box at 128x128 (16k pixels) fell from relMSE
# 0.00083 at 100k photons an iteration to 0.00045 at 25k; Sponza at 320x240
# (77k pixels) is best from 100k to 200k and worse at 50k (0.00274 against
# 0.00204). 1.5 per pixel gives 25k and 115k (docs/accuracy.md).
PHOTONS_PER_PIXEL = 1.5
MIN_PHOTONS_PER_ITERATION = 10_000


@dataclass
class RenderSettings:
    seed: int = 0
    alpha: float = 0.7
    radius: float | None = None          # initial radius; None: from scene size and pixels
    # Scattering events a light path may have, the hit point's included (0:
    # emitters seen directly; 1: direct light, and emitters in a mirror). Russian roulette ends paths, unbiased; this
    # is only a safety net for light trapped in glass by total internal
    # reflection (roulette keeps it: glass absorbs nothing). At 256 the
    # paths it cuts change no pixel by 1e-4 of the brightest
    # (tests/test_render.py); at 64, 0.2% of the mean was lost in a glass
    # scene. The paper's setting is 10.
    max_depth: int = 256
    gather: str = "grid"                 # 'grid' (exact) or 'hash' (stochastic, HJ10)
    photons_per_iteration: int | None = None   # None: PHOTONS_PER_PIXEL x pixels (`for_image`)
    photons_per_job: int = 8_192
    photon_batch: int = 1_000_000        # deposits per statistics update (server batching)
    tile_pixels: int = 16_384            # eye rays per eye job
    threads: int = 2
    reorder: bool = True                 # Morton-sort photons before the gather
    cull: bool = True                    # drop photons outside the hit-point box (§4.3)
    hash_options: dict = field(default_factory=dict)
    # Direct light at hit points: 'nee' (a shadow ray per hit point and
    # iteration; photons deposit from their second surface on) or
    # 'photons' (the paper's pure estimator: every photon deposits).
    direct: str = "nee"
    # Bytes of the light cache each rendering process learns from the
    # photons' first hits (which lights reach where; kernels/light_cache.py),
    # counted in its memory for chunks; 0: the light tree alone.
    light_cache: int = LIGHT_CACHE_BYTES

    def for_image(self, pixels: int) -> RenderSettings:
        """These settings with photons per iteration fixed for an image of
        `pixels` pixels (unchanged where given)."""
        if self.photons_per_iteration is not None:
            return self
        n = max(MIN_PHOTONS_PER_ITERATION, round(PHOTONS_PER_PIXEL * pixels))
        return dataclasses.replace(self, photons_per_iteration=n)

    @property
    def deposit_from(self) -> int:
        """The first surface (0-based) a photon deposits at: with shadow
        rays carrying direct light, photons deposit only from their second
        surface on, so no light is counted twice."""
        return 1 if self.direct == "nee" else 0

    def validate(self) -> None:
        if not 0 < self.alpha < 1:
            raise ValueError(f"alpha must lie in (0, 1), got {self.alpha}")
        if self.max_depth < 0:
            raise ValueError(f"max_depth must be >= 0, got {self.max_depth}")
        if self.direct not in DIRECT_MODES:
            raise ValueError(f"direct must be one of {', '.join(DIRECT_MODES)}, got {self.direct!r}")
        if self.gather not in ("grid", "hash"):
            raise ValueError(f"gather must be 'grid' or 'hash', got {self.gather!r}")
        for name in ("photons_per_iteration", "photons_per_job", "photon_batch", "tile_pixels"):
            if getattr(self, name) is not None and getattr(self, name) < 1:
                raise ValueError(f"{name} must be >= 1")
        if self.radius is not None and not self.radius > 0:
            raise ValueError(f"radius must be > 0, got {self.radius}")


# Mitsuba integrators whose light transport ours estimates (volumes aside:
# a scene with media is refused by the reader).
MITSUBA_INTEGRATORS = ("path", "ptracer", "direct", "volpath", "volpathmis")


def scene_settings(hints: dict) -> dict:
    """The RenderSettings fields a scene file's integrator fixes (from
    `scene.render_settings`; {} when it names none). Mitsuba's `max_depth`
    counts the vertices of a path after the camera, the emitter's included:
    1 is emitters seen directly, 2 direct light, -1 unbounded. Ours counts
    scattering events (`RenderSettings.max_depth`), so ours = Mitsuba's - 1,
    and unbounded is our default (roulette ends paths). `direct` is `path`
    at depth 2 (emission, then light sampled and BSDF-sampled at the first
    hit: no chain beyond); `ptracer` carries the same transport as `path`."""
    kind = hints.get("integrator")
    if kind is None:
        return {}
    if hints.get("hide_emitters"):
        raise ValueError("hide_emitters: emitters seen directly cannot be hidden (we render them)")
    if kind not in MITSUBA_INTEGRATORS:
        raise ValueError(f"integrator {kind!r} is not one we render (known: {', '.join(MITSUBA_INTEGRATORS)})")
    depth = 2 if kind == "direct" else int(hints.get("max_depth", -1))
    if depth == 0:
        raise ValueError("max_depth 0 renders nothing (Mitsuba's depth counts the emitter: 1 shows emitters)")
    return {"max_depth": RenderSettings.max_depth if depth < 0 else depth - 1}


# One process runs few large jobs (RenderSettings' 8192 photons a job, 16384
# pixels an eye tile: fewer kernel calls). The DOSPPM service cuts them
# finer, so that the ~1000 jobs it keeps in flight spread over every tracer
# and each result message stays small. Photon jobs of 4,096, not 1,024:
# the server and tracers pay Python per job and per (job, chunk) part, and
# on the 5M building (2 tracers, 8 chunks, 60 s) 4,096 applied 898-919k
# photons/s out of core against 601-828k, and 822-854k with every chunk
# resident against 728-763k; 8,192 gained nothing more (880k, 835k).
SERVICE_JOB_SIZES = {"photons_per_job": 4_096, "tile_pixels": 4_096}
# Gathering at the tracers (issue 32) a photon job is only (id, rng key,
# count) and its deposits stay at the tracer: the server pays per job for
# making, sending and accounting it, and nothing per deposit. Jobs of one
# tracer step's 16,384 photons fed 23.7 tracer cores per server core in the
# replay against 20.1 at 4,096 (medians of 3, cornell-glass, 2 tracers).
GATHER_AT_TRACERS_PHOTONS_PER_JOB = 16_384


def service_job_sizes(gather_at: str | None = "server") -> dict:
    """The service's default job sizes, for where photons are gathered."""
    if gather_at == "tracers":
        return dict(SERVICE_JOB_SIZES, photons_per_job=GATHER_AT_TRACERS_PHOTONS_PER_JOB)
    return dict(SERVICE_JOB_SIZES)
# A scene cut into chunks on the fly (a soup directory, `--chunks`): memory
# per chunk, and where the store is kept for the next render.
DEFAULT_BUDGET_BYTES = 512 * 2 ** 20


def default_store_cache() -> str:
    base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return os.path.join(base, "dosppm", "chunks")


@dataclass
class Progress:
    """Where a render stands after an iteration (what the progress line,
    the JSON-lines log and the status page show)."""
    iteration: int
    photons_emitted: int
    hit_points: int
    seconds: float
    path_ends: dict
