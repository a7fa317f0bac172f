"""The server's pixel statistics: `state.Update`s applied in order (hit
points of complete eye iterations, batches of photons of complete jobs)
through the library's `SPPMIteration`, the same steps single-process SPPM
and OSPPM take. The server shell runs this on its own thread; the kernels
release the GIL, so the message loop keeps going meanwhile."""
from __future__ import annotations

import threading
import time

import numpy as np

from dosppm_core.settings import RenderSettings
from dosppm_core.sppm.iteration import SPPMIteration
from services.ledger import Ledger
from services.server import checkpoint
from services.server.costs import thread_cpu


class ServerStatistics:
    def __init__(self, header, settings: RenderSettings, threads: int, ledger: Ledger | None = None):
        """`ledger`: where every applied update is recorded (services/ledger.py)."""
        self.header, self.settings, self.threads = header, settings, threads
        self.sppm = SPPMIteration(header, settings, threads=threads)
        self.lock = threading.Lock()       # held while statistics change; snapshots take it
        self.update_seconds = 0.0
        # This thread's CPU in updates; the kernels' parallel workers are
        # not in it (costs.py).
        self.update_cpu_s = 0.0
        self.photon_update_s = 0.0         # the last batch of photons took (the deadline's reserve)
        self.ledger = ledger

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
            elif update.kind == "hits":
                self.sppm.install_hit_points(update.hits, update.emitted_light)
            else:
                # The state already cut this batch at `photon_batch` deposits
                # (only complete jobs count), so it is one update.
                self.sppm.apply_photon_batch(update.deposits, update.photons_emitted)
            if self.ledger is not None:
                self.ledger.record(update)
            box = self.sppm.cull_box() if self.sppm.has_hit_points else None
        took = time.perf_counter() - t0
        self.update_seconds += took
        if update.kind == "photons":
            self.photon_update_s = took
        return box

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
