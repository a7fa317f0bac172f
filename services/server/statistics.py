"""The server's pixel statistics: `scheduler.Update`s applied in order
(hit points of complete eye iterations, batches of photons of complete
jobs) to the library's `PixelStatistics` (eqs. 1-5). The server shell runs
this on its own thread; the kernels release the GIL, so the message loop
keeps going meanwhile."""
from __future__ import annotations

import threading
import time

import numpy as np

from dosppm_core.modes.sppm import RenderSettings
from dosppm_core.sppm.statistics import PixelStatistics, initial_radius

from services.server import checkpoint


class ServerStatistics:
    def __init__(self, header, settings: RenderSettings, threads: int):
        cam = header.camera
        self.header, self.settings, self.threads = header, settings, threads
        self.stats = PixelStatistics(int(cam.width), int(cam.height), settings.radius, settings.alpha)
        self.lock = threading.Lock()       # held while statistics change; snapshots take it
        self.update_seconds = 0.0
        self.photons_applied = 0
        self.deposits_applied = 0

    def apply(self, update) -> np.ndarray | None:
        """Run one update; returns the new photon culling box (§4.3)."""
        t0 = time.perf_counter()
        with self.lock:
            if update.kind == "checkpoint":
                checkpoint.write(update.directory, self.stats, update.meta)
            elif update.kind == "hits":
                self._install_hits(update)
            else:
                self._apply_photons(update)
            box = self.stats.gather_box() if self.stats.has_radius else None
        self.update_seconds += time.perf_counter() - t0
        return box

    def _install_hits(self, update) -> None:
        if not self.stats.has_radius:
            self.stats.set_initial_radius(initial_radius(self.header, update.hits))
        self.stats.replace_hit_points(update.hits, update.emitted_light)

    def _apply_photons(self, update) -> None:
        """One statistics update for the whole batch: the state already cut
        it at `photon_batch` deposits (or merged several at the end)."""
        s, deposits = self.settings, update.deposits
        self.stats.apply_photons(deposits, update.photons_emitted, self.header.materials,
                                 gather=s.gather, threads=self.threads, reorder=s.reorder,
                                 hash_options=s.hash_options)
        self.photons_applied += update.photons_emitted
        self.deposits_applied += len(deposits)

    def image(self) -> np.ndarray:
        with self.lock:
            return self.stats.radiance().astype(np.float32)

    def layers(self) -> dict:
        with self.lock:
            h, w = self.stats.height, self.stats.width
            return {"radius": self.stats.radius.reshape(h, w).astype(np.float32),
                    "photon_count": self.stats.photon_count.reshape(h, w).astype(np.float32)}
