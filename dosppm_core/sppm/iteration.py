"""The SPPM iteration, written once for every mode (Günther & Grosch §3.2-3.3, §4.3).

Single-process SPPM, OSPPM and the DOSPPM server differ only in how rays
reach the kernels and how results come back. What they do with those
results is the same, and lives here:

- An eye pass's results (hit points, and emission its eye rays saw
  directly) arrive tile by tile, from any chunk or tracer and in any order;
  `EyePass` collects them, and `SPPMStatistics.install_eye_pass` replaces
  the hit points once the pass is complete, and starts the radius of each
  pixel no photon has reached yet at a pilot radius; the first batch that
  reaches it fits it to the photon density there (`PixelStatistics.fit_radii`).
- Photons are emitted against the current hit points: `cull_box` is their
  box grown by the largest radius (§4.3), or no box at all when culling is
  off (the DOSPPM server emits no photons before the first hit points).
- Deposits are applied to the pixel statistics in batches of at most
  `photon_batch` deposits (server batching, §4.3), each with the number of
  photons emitted for it (N_e; only the total matters for eq. 5).

A new kind of contribution to a pixel (for example direct light carried by
shadow rays) is added here once, as another `install_*`/`apply_*` step,
and every mode reaches it.
"""
from __future__ import annotations

import time

import numpy as np

from dosppm_core.jobs import END_NAMES, HitPoints, PhotonDeposits
from dosppm_core.settings import Progress, RenderSettings
from dosppm_core.sppm.statistics import PixelStatistics, pilot_radius, pixel_footprint
from dosppm_core.trace import NO_CULL


def hit_point_stride(photons_per_update: int, photons_per_iteration: int) -> int:
    """One eye iteration in how many installs its hit points, where eye
    iterations run beside the photons (the DOSPPM server): a set of hit
    points is gathered at by the statistics updates made while it is
    installed, and an update is about `photons_per_update` photons, so a
    set installed every `photons_per_iteration` photons (one eye iteration)
    would mostly be replaced before any update read it. The others still
    count for the emission and direct light their paths saw. Which
    iterations install is fixed by their index alone, never by what they
    saw, so the estimate stays unbiased."""
    return max(1, int(photons_per_update) // max(1, int(photons_per_iteration)))


def keeps_hit_points(eye_iteration: int, stride: int) -> bool:
    """Whether eye iteration `eye_iteration` installs its hit points (see
    `hit_point_stride`): the first does, so photons have a box to go by."""
    return int(eye_iteration) % max(1, int(stride)) == 0


class EyePass:
    """The results of one eye iteration, gathered as its tiles complete."""

    def __init__(self, index: int = 0):
        self.index = index
        self.hits: list[HitPoints] = []
        self.pixels: list[np.ndarray] = []
        self.rgb: list[np.ndarray] = []

    def add(self, hits: HitPoints, pixels: np.ndarray, rgb: np.ndarray) -> None:
        """One traced tile (or part of one): its hit points, and the
        emission its eye rays saw, per pixel (None: held elsewhere)."""
        self.hits.append(hits)
        if pixels is not None:
            self.pixels.append(pixels)
            self.rgb.append(rgb)

    def complete(self) -> tuple[HitPoints, tuple[np.ndarray, np.ndarray]]:
        """(hit points, (pixel, rgb) of directly seen emission)."""
        pixels = np.concatenate(self.pixels) if self.pixels else np.empty(0, np.int32)
        rgb = np.concatenate(self.rgb) if self.rgb else np.empty((0, 3), np.float32)
        return HitPoints.concat(self.hits), (pixels, rgb)


class SPPMStatistics:
    """The pixel statistics of a whole render and the steps every mode
    applies to them. `header` is a SceneHeader (camera, materials, bounds): not a
    Scene, whose bounds() reads every vertex, and each eye pass needs the
    diagonal (0.29 s of a 0.36 s eye pass on a 2M-triangle building)."""

    def __init__(self, header, settings: RenderSettings, threads: int | None = None):
        cam = header.camera
        self.header, self.settings = header, settings
        self.threads = settings.threads if threads is None else threads
        self.stats = PixelStatistics(int(cam.width), int(cam.height), settings.radius, settings.alpha)
        self.path_ends = np.zeros(len(END_NAMES), np.int64)
        self.hit_point_total = 0
        self.photons_applied = 0
        self.deposits_applied = 0
        self.flux_applied = np.zeros(3)       # of every deposit applied, float64
        self.update_seconds = 0.0
        self.updates = 0                      # photon batches applied
        self._pending: list[PhotonDeposits] = []
        self._pending_rows = 0
        self._pending_emitted = 0

    # -- eye passes --------------------------------------------------------------
    def install_eye_pass(self, eye: EyePass) -> int:
        """Replace the hit points by those of a complete eye pass; returns
        how many there were."""
        hits, seen_light = eye.complete()
        self.install_hit_points(hits, seen_light)
        return len(hits)

    def add_eye_emission(self, seen_light: tuple) -> None:
        """A complete eye iteration whose hit points are not installed
        (`keeps_hit_points`): only the emission its paths saw counts."""
        self.stats.add_emission(seen_light)

    def add_eye_light(self, rgb: np.ndarray, eye_iterations: int) -> None:
        """The light of `eye_iterations` complete eye iterations, summed per
        pixel by whoever held it (the DOSPPM tracers); their hit points
        were installed without it (`install_hit_points(hits, None)`)."""
        self.stats.add_light(rgb, eye_iterations)

    def install_hit_points(self, hits: HitPoints, seen_light: tuple | None) -> None:
        if self.settings.radius is None:      # else fixed by --radius for every pixel
            self.stats.fit_radii(hits.pixel, pilot_radius(hits), pixel_footprint(self.header, hits))
        self.stats.replace_hit_points(hits, seen_light)
        self.hit_point_total += len(hits)

    @property
    def has_hit_points(self) -> bool:
        return len(self.stats.hit_points) > 0

    def cull_box(self) -> np.ndarray:
        """The box photons emitted now are culled against (§4.3): the hit
        points grown by the largest radius; NO_CULL when culling is off or
        there are no hit points yet."""
        if not (self.settings.cull and self.has_hit_points):
            return NO_CULL
        return self.stats.gather_box()

    # -- photon batches ----------------------------------------------------------
    def add_photons(self, deposits: PhotonDeposits, emitted: int) -> None:
        """Deposits of `emitted` photon paths that have all ended. Each time
        `photon_batch` deposits wait, they are applied (server batching), so
        a caller may hand them over as they are made: what waits is at most
        one batch, never an iteration's worth."""
        self._pending.append(deposits)
        self._pending_rows += len(deposits)
        self._pending_emitted += int(emitted)
        while self._pending_rows >= self.settings.photon_batch:
            self._apply_pending(self.settings.photon_batch)

    def flush(self) -> None:
        """Apply every waiting deposit, in batches of at most `photon_batch`."""
        if not self._pending_emitted and not self._pending_rows:
            return
        while True:     # once at least: photons emitted with no deposit count too
            self._apply_pending(min(self._pending_rows, self.settings.photon_batch))
            if not self._pending_rows:
                return

    def _apply_pending(self, rows: int) -> None:
        """The first `rows` waiting deposits as one batch, as the parts they
        came in (no copy), counted with every photon emitted since the last."""
        batch, self._pending = cut_parts(self._pending, rows)
        self._pending_rows -= rows
        emitted, self._pending_emitted = self._pending_emitted, 0
        self.apply_photon_batch(batch or [PhotonDeposits.empty()], emitted)

    def apply_photon_batch(self, deposits: PhotonDeposits | list, emitted: int) -> None:
        """One statistics update (eqs. 1-4) of a PhotonDeposits or a list
        of parts. The server calls this directly: its state cuts batches
        itself, since only complete jobs count, and hands them over as the
        parts they arrived in (no copy)."""
        t0 = time.perf_counter()
        s = self.settings
        self.stats.apply_photons(deposits, emitted, self.header.materials, gather=s.gather,
                                 threads=self.threads, reorder=s.reorder,
                                 hash_options=s.hash_options)
        parts = deposits if isinstance(deposits, list) else [deposits]
        self.photons_applied += int(emitted)
        self.deposits_applied += sum(len(p) for p in parts)
        for p in parts:
            self.flux_applied += p.flux.sum(axis=0, dtype=np.float64)
        self.update_seconds += time.perf_counter() - t0
        self.updates += 1

    def apply_sums(self, m: np.ndarray, phi: np.ndarray, emitted: int, deposits: int, flux) -> None:
        """One statistics update (eqs. 1-4) from a batch gathered elsewhere:
        per hit point (of the installed set, in its order) M and Phi at the
        current radii, summed over the tracers that held the batch, with
        how many deposits that was and their flux (the totals' ledger)."""
        t0 = time.perf_counter()
        self.stats.apply_sums(self.stats.hit_points.pixel, m, phi, emitted)
        self.photons_applied += int(emitted)
        self.deposits_applied += int(deposits)
        self.flux_applied += np.asarray(flux, np.float64)
        self.update_seconds += time.perf_counter() - t0
        self.updates += 1

    def restore_totals(self, totals: dict) -> None:
        """The counts of `totals` of a checkpointed render (its statistics
        are restored on their own), so a resumed render's totals are the
        whole render's."""
        self.hit_point_total = int(totals["hit_points"])
        self.deposits_applied = int(totals["deposits"])
        self.flux_applied = np.asarray(totals["flux"], np.float64)

    def totals(self) -> dict:
        """What the statistics hold in all: N_e, hit points installed,
        deposits applied and their flux, N and tau summed over the pixels.
        Two renders of the same steps agree on these up to summation order
        (services/ledger.py compares a server's with a re-trace's)."""
        st = self.stats
        return {"photons_emitted": int(st.photons_emitted), "hit_points": int(self.hit_point_total),
                "deposits": int(self.deposits_applied), "flux": self.flux_applied.tolist(),
                "N": float(st.photon_count.sum()), "tau": st.tau.sum(axis=0).tolist()}

    # -- what a render shows -------------------------------------------------------
    def count_path_ends(self, ends: np.ndarray) -> None:
        self.path_ends += ends

    def progress(self, iteration: int, seconds: float) -> Progress:
        ends = {name: int(c) for name, c in zip(END_NAMES, self.path_ends) if name != "continues"}
        return Progress(iteration, self.stats.photons_emitted, self.hit_point_total, seconds, ends)

    def image(self) -> np.ndarray:
        """Radiance (H, W, 3) float32 (eq. 5)."""
        return self.stats.radiance().astype(np.float32)

    def layers(self) -> dict:
        """Per-pixel radius and photon count, for the EXR's extra layers."""
        h, w = self.stats.height, self.stats.width
        return {"radius": self.stats.radius.reshape(h, w).astype(np.float32),
                "photon_count": self.stats.photon_count.reshape(h, w).astype(np.float32)}


def cut_parts(parts: list, rows: int) -> tuple[list, list]:
    """`parts` (records) cut after `rows` rows: (the first rows' parts, the
    rest), a part straddling the cut sliced (views, no copy)."""
    head, n = [], 0
    for i, part in enumerate(parts):
        if n + len(part) > rows:
            cut = rows - n
            rest = ([part.slice(cut, len(part))] if cut else [part]) + parts[i + 1:]
            return head + ([part.slice(0, cut)] if cut else []), rest
        head.append(part)
        n += len(part)
    return head, []
