"""Single-process SPPM: the baseline every other mode is measured against.

One iteration traces an eye pass (hit points of every pixel, in tiles) and
a photon pass (emission jobs traced to completion), applying deposits to the
pixel statistics in batches. The out-of-core and distributed modes reuse
the same jobs, steps and statistics with another transport in between.
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np

from dosppm_core.accel import Accelerator
from dosppm_core.jobs import END_NAMES, HitPoints, PhotonDeposits
from dosppm_core.scene.model import Scene
from dosppm_core.sppm.statistics import PixelStatistics, initial_radius
from dosppm_core.trace import NO_CULL, SurfaceData, emit_photon_job, eye_ray_job, trace_eye, trace_photon_jobs


@dataclass
class RenderSettings:
    seed: int = 0
    alpha: float = 0.7
    radius: float | None = None          # initial radius; None: from scene size and pixels
    max_depth: int = 10                  # surfaces a path may hit (the paper's 10)
    gather: str = "grid"                 # 'grid' (exact) or 'hash' (stochastic, HJ10)
    photons_per_iteration: int = 100_000
    photons_per_job: int = 8_192
    photon_batch: int = 1_000_000        # deposits per statistics update (server batching)
    tile_pixels: int = 16_384            # eye rays per eye job
    threads: int = 2
    reorder: bool = True                 # Morton-sort photons before the gather
    cull: bool = True                    # drop photons outside the hit-point box (§4.3)
    hash_options: dict = field(default_factory=dict)

    def validate(self) -> None:
        if not 0 < self.alpha < 1:
            raise ValueError(f"alpha must lie in (0, 1), got {self.alpha}")
        if self.max_depth < 1:
            raise ValueError(f"max_depth must be >= 1, got {self.max_depth}")
        if self.gather not in ("grid", "hash"):
            raise ValueError(f"gather must be 'grid' or 'hash', got {self.gather!r}")
        for name in ("photons_per_iteration", "photons_per_job", "photon_batch", "tile_pixels"):
            if getattr(self, name) < 1:
                raise ValueError(f"{name} must be >= 1")
        if self.radius is not None and not self.radius > 0:
            raise ValueError(f"radius must be > 0, got {self.radius}")


@dataclass
class Progress:
    iteration: int
    photons_emitted: int
    hit_points: int
    seconds: float
    path_ends: dict


class Renderer:
    """Drives iterations of SPPM over one scene in this process."""

    def __init__(self, scene: Scene, settings: RenderSettings | None = None):
        self.scene = scene
        self.settings = settings or RenderSettings()
        self.settings.validate()
        s = self.settings
        cam = scene.camera
        self.accel = Accelerator(scene.vertices, scene.triangles, threads=s.threads)
        self.surf = SurfaceData.from_scene(scene)
        self.stats = PixelStatistics(int(cam.width), int(cam.height), s.radius, s.alpha)
        self.iteration = 0
        self.next_photon_job = 0
        self.path_ends = np.zeros(len(END_NAMES), np.int64)
        self.hit_point_total = 0
        self.seconds = 0.0
        self._pending: list[PhotonDeposits] = []
        self._pending_count = 0
        self._pending_emitted = 0

    def run_iteration(self) -> Progress:
        t0 = time.perf_counter()
        self._eye_pass()
        self._photon_pass()
        self._apply_pending()
        self.iteration += 1
        self.seconds += time.perf_counter() - t0
        return self.progress()

    def progress(self) -> Progress:
        ends = {name: int(c) for name, c in zip(END_NAMES, self.path_ends) if name != "continues"}
        return Progress(self.iteration, self.stats.photons_emitted, self.hit_point_total,
                        self.seconds, ends)

    def image(self) -> np.ndarray:
        return self.stats.radiance().astype(np.float32)

    # -- passes ---------------------------------------------------------------
    def _eye_pass(self) -> None:
        s, cam = self.settings, self.scene.camera
        n_pix = int(cam.width) * int(cam.height)
        hits, pix, rgb = [], [], []
        for start in range(0, n_pix, s.tile_pixels):
            batch = eye_ray_job(self.scene, s.seed, self.iteration, start,
                                min(s.tile_pixels, n_pix - start))
            h, (p, e), _ends = trace_eye(self.accel, self.surf, batch, s.max_depth)
            hits.append(h)
            pix.append(p)
            rgb.append(e)
        hp = HitPoints.concat(hits)
        self.hit_point_total += len(hp)
        if not self.stats.has_radius:
            self.stats.set_initial_radius(initial_radius(self.scene, hp))
        self.stats.replace_hit_points(hp, (np.concatenate(pix), np.concatenate(rgb)))

    def _photon_pass(self) -> None:
        s = self.settings
        box = self.stats.gather_box() if s.cull else None
        cull = NO_CULL if box is None else box
        left = s.photons_per_iteration
        while left > 0:
            # Trace up to one server batch worth of photons as one stream.
            count = min(left, max(s.photon_batch // 2, s.photons_per_job))
            deposits, ends, _culled = trace_photon_jobs(
                self.accel, self.surf, self._jobs(count), cull, s.max_depth)
            self.path_ends += ends
            self._pending.append(deposits)
            self._pending_count += len(deposits)
            self._pending_emitted += count
            left -= count
            if self._pending_count >= s.photon_batch:
                self._apply_pending()

    def _jobs(self, photons: int):
        """Emission jobs for `photons` photons, numbered globally so a job
        id always names the same photons."""
        s = self.settings
        while photons > 0:
            count = min(s.photons_per_job, photons)
            yield emit_photon_job(self.scene, s.seed, self.next_photon_job, count,
                                  self.surf.eps_abs)
            self.next_photon_job += 1
            photons -= count

    def _apply_pending(self) -> None:
        if not self._pending_emitted:
            return
        s = self.settings
        deposits = PhotonDeposits.concat(self._pending)
        self.stats.apply_photons(deposits, self._pending_emitted, self.scene.materials,
                                 gather=s.gather, threads=s.threads, reorder=s.reorder,
                                 hash_options=s.hash_options)
        self._pending, self._pending_count, self._pending_emitted = [], 0, 0

    def close(self) -> None:
        self.accel.close()


def render(scene: Scene, settings: RenderSettings | None = None, *, iterations: int | None = None,
           photons: int | None = None, seconds: float | None = None, on_progress=None) -> np.ndarray:
    """Render until any given limit is reached (at least one iteration)."""
    r = Renderer(scene, settings)
    try:
        while True:
            p = r.run_iteration()
            if on_progress:
                on_progress(p)
            if iterations is not None and p.iteration >= iterations:
                break
            if photons is not None and p.photons_emitted >= photons:
                break
            if seconds is not None and p.seconds >= seconds:
                break
            if iterations is None and photons is None and seconds is None:
                break
        return r.image()
    finally:
        r.close()
