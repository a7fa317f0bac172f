"""The server's pixel statistics: `state.Update`s applied in order (hit
points of complete eye iterations, batches of photons of complete jobs)
through the library's `SPPMStatistics`, the same steps single-process SPPM
and OSPPM take. The server shell runs this on its own thread; the kernels
release the GIL, so the message loop keeps going meanwhile."""
from __future__ import annotations

import threading
import time

import numpy as np

from dosppm_core.settings import RenderSettings
from dosppm_core.sppm.iteration import SPPMStatistics
from services.ledger import Ledger
from services.server import checkpoint
from services.server.costs import thread_cpu


def moves_box(update) -> bool:
    """Whether `update` may change the hit points or their radii, and so
    the cull box and the mean radius: most updates do not (an eye
    iteration that keeps no hit points, a gather's round, eye light, a
    checkpoint), and at one eye iteration per 98k photons the box of 65k
    hit points, made again after each, was a share of the server's CPU."""
    return update.kind in ("photons", "epoch") or (update.kind == "hits" and update.hits is not None)


class ServerStatistics:
    def __init__(self, header, settings: RenderSettings, threads: int, ledger: Ledger | None = None):
        """`ledger`: where every applied update is recorded (services/ledger.py)."""
        self.header, self.settings, self.threads = header, settings, threads
        self.sppm = SPPMStatistics(header, settings, threads=threads)
        self.lock = threading.Lock()       # held while statistics change; snapshots take it
        self.update_seconds = 0.0
        # This thread's CPU in updates; the kernels' parallel workers are
        # not in it (costs.py).
        self.update_cpu_s = 0.0
        self.photon_update_s = 0.0         # the last batch of photons took (the deadline's reserve)
        self.ledger = ledger
        self.hits_version: int | None = None     # the eye iteration whose hit points are installed
        self._box: np.ndarray | None = None      # the cull box, as the last update that moved it left it

    @property
    def stats(self):
        return self.sppm.stats

    @property
    def photons_applied(self) -> int:
        return self.sppm.photons_applied

    @property
    def deposits_applied(self) -> int:
        return self.sppm.deposits_applied

    @thread_cpu("update_cpu_s")
    def apply(self, update) -> np.ndarray | None:
        """Run one update; returns the cull box for photons emitted from
        now on (§4.3), None while there are no hit points yet."""
        t0 = time.perf_counter()
        with self.lock:
            if update.kind == "checkpoint":
                # Where a resumed render's ledger goes on from (see Ledger).
                meta = update.meta if self.ledger is None else dict(
                    update.meta, ledger_records=self.ledger.count, ledger_totals=self.sppm.totals())
                checkpoint.write(update.directory, self.sppm.stats, meta)
            elif update.kind == "light":
                self.sppm.add_eye_light(update.light, update.light_iterations)
            elif update.kind == "hits" and update.hits is None:
                if update.emitted_light is not None:
                    self.sppm.add_eye_emission(update.emitted_light)
            elif update.kind == "hits":
                self.sppm.install_hit_points(update.hits, update.emitted_light)
                update.installed = self.sppm.stats.hit_points
                self.hits_version = update.eye_iteration
            elif update.kind == "gather":
                update.request = self._gather_request(update)
            elif update.kind == "epoch":
                self._apply_epoch(update)
            else:
                # The state already cut this batch at `photon_batch` deposits
                # (only complete jobs count), so it is one update.
                self.sppm.apply_photon_batch(update.deposits, update.photons_emitted)
            if self.ledger is not None:
                self.ledger.record(update)
            if moves_box(update) or self._box is None:
                self._box = self.sppm.cull_box() if self.sppm.has_hit_points else None
            box = self._box
        took = time.perf_counter() - t0
        self.update_seconds += took
        if update.kind in ("photons", "epoch"):
            self.photon_update_s = took
        return box

    def _gather_request(self, u) -> dict | None:
        """The `gather` fields of epoch `u.epoch`'s next round after
        `u.stage` (docs/how-it-works.md, "The gather at the tracers"): a
        count first when a pilot will be needed (its subsample's cut needs
        the epoch's deposit count), then the pilot, then the sums at the
        radii the pixels have now, fitted ones included. None for an epoch
        discarded meanwhile."""
        e, st = u.epoch, self.sppm.stats
        if e.phase == "discarded":
            return None
        ids, _keys, _paths, boxes = e.columns()
        base = dict(epoch=e.index, epochs=e.count, hits_version=self.hits_version, job_ids=ids, job_boxes=boxes)
        pilot = st.pilot_request()
        if u.stage == "start" and pilot is not None:
            return dict(base, phase="count", rows=np.zeros(0, np.int64), radius=np.zeros(0))
        if u.stage == "count" and pilot is not None and u.sums["deposits"] > 0:
            fresh, r_pilot, most = pilot
            return dict(base, phase="pilot", total=u.sums["deposits"], most=most, rows=fresh.astype(np.int64),
                        radius=r_pilot)
        if u.stage == "pilot":
            fresh, r_pilot, _most = pilot
            e.fit = st.fitted_radii(fresh, r_pilot, u.sums["m"], u.sums["chosen"])
        radius = st.radius.copy()
        if e.fit is not None:
            radius[e.fit[0]] = e.fit[1]
        hp = st.hit_points
        return dict(base, phase="sums", rows=np.arange(len(hp), dtype=np.int64), radius=radius[hp.pixel])

    def _apply_epoch(self, u) -> None:
        """An epoch's summed sums, after the radii fitted for it."""
        e, s = u.epoch, u.sums
        if e.fit is not None:
            self.sppm.stats.commit_fit(*e.fit)
        self.sppm.apply_sums(s["m"], s["phi"], u.photons_emitted, s["deposits"], s["flux"])

    def end_ledger(self, deposits_late: int) -> None:
        """The totals, once every update is applied (the ledger's last
        record), with the deposits the state dropped because their job was
        already complete (none, by credit: services/credit.py)."""
        if self.ledger is not None:
            with self.lock:
                self.ledger.end(dict(self.sppm.totals(), deposits_late=int(deposits_late)))

    def image(self) -> np.ndarray:
        with self.lock:
            return self.sppm.image()

    def layers(self) -> dict:
        with self.lock:
            return self.sppm.layers()
