"""Single-process SPPM: the baseline every other mode is measured against.

One iteration traces an eye pass (hit points of every pixel, in tiles) and
a photon pass (emission jobs traced to completion), applying deposits to the
pixel statistics in batches. The out-of-core and distributed modes reuse
the same jobs, steps and statistics with another transport in between.
"""
from __future__ import annotations

import time

import numpy as np

from dosppm_core.accel import Accelerator
from dosppm_core.kernels.light_cache import LightCache
from dosppm_core.modes.deadline import Deadline, Rate, that_fit
from dosppm_core.scene.model import Scene
from dosppm_core.settings import Progress, RenderSettings
from dosppm_core.sppm.iteration import EyePass, SPPMStatistics
from dosppm_core.trace import (SurfaceData, emit_photon_job, environment, eye_ray_job, freeze_light_cache,
                               light_arrays, trace_eye, trace_photon_jobs)


class Renderer:
    """Drives iterations of SPPM over one scene in this process."""

    def __init__(self, scene: Scene, settings: RenderSettings | None = None):
        self.scene = scene
        self.settings = (settings or RenderSettings()).for_image(scene.camera.width * scene.camera.height)
        self.settings.validate()
        self.accel = Accelerator(scene.vertices, scene.triangles, threads=self.settings.threads)
        self.surf = SurfaceData.from_scene(scene)
        self.lights = light_arrays(scene.lights, LightCache(scene.bounds(), self.settings.light_cache, frozen=True)) \
            if self.settings.direct == "nee" else None
        self.env = environment(scene.lights)
        self.sppm = SPPMStatistics(scene.header(), self.settings)
        self.iteration = 0
        self.next_photon_job = 0
        self.seconds = 0.0
        self.eye_seconds = 0.0                # the last eye pass's
        self.photon_rate = Rate()             # photons traced and applied per second

    def worth_an_iteration(self, deadline: Deadline | None) -> bool:
        """Whether another iteration can start: always the first; then only
        while its eye pass would end before the deadline (photons after it
        are sized to the time left)."""
        return deadline is None or self.iteration == 0 or deadline.left() > self.eye_seconds

    @property
    def stats(self):
        return self.sppm.stats

    def run_iteration(self, deadline: Deadline | None = None) -> Progress:
        """One iteration; with a `deadline`, its photons are only as many as
        can be traced and applied before it (fewer, or none, near the end:
        N_e counts the photons applied)."""
        t0 = time.perf_counter()
        self._eye_pass()
        self.eye_seconds = time.perf_counter() - t0
        self._photon_pass(deadline)
        self.sppm.flush()
        self.iteration += 1
        self.seconds += time.perf_counter() - t0
        return self.progress()

    def progress(self) -> Progress:
        return self.sppm.progress(self.iteration, self.seconds)

    def image(self) -> np.ndarray:
        return self.sppm.image()

    # -- passes ---------------------------------------------------------------
    def _eye_pass(self) -> None:
        s, cam = self.settings, self.scene.camera
        n_pix = int(cam.width) * int(cam.height)
        eye = EyePass(self.iteration)
        freeze_light_cache(self.lights)
        for start in range(0, n_pix, s.tile_pixels):
            batch = eye_ray_job(self.scene, s.seed, self.iteration, start,
                                min(s.tile_pixels, n_pix - start))
            hits, (pixels, rgb), _ends = trace_eye(self.accel, self.surf, batch, s.max_depth,
                                                   self.lights, self.env)
            eye.add(hits, pixels, rgb)
        self.sppm.install_eye_pass(eye)

    def _photon_pass(self, deadline: Deadline | None) -> None:
        s = self.settings
        cull = self.sppm.cull_box()
        left = s.photons_per_iteration
        while left > 0:
            # Trace up to half a statistics batch of photons as one stream,
            # as many whole jobs as end before the deadline.
            count = that_fit(None if deadline is None else deadline.left(),
                             min(left, max(s.photon_batch // 2, s.photons_per_job)),
                             self.photon_rate.per_s, s.photons_per_job)
            if count <= 0:
                return
            t0 = time.perf_counter()
            deposits, ends, _culled = trace_photon_jobs(
                self.accel, self.surf, self._jobs(count), cull, s.max_depth,
                deposit_from=s.deposit_from, lights=self.lights)
            self.sppm.count_path_ends(ends)
            self.sppm.add_photons(deposits, count)
            self.photon_rate.add(count, time.perf_counter() - t0)
            left -= count

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
