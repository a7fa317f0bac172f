"""A tracer's share of the gather, by epochs (issue 32 step 3; the
derivation is in docs/how-it-works.md, "The gather at the tracers").

An epoch is a fixed range of photon job ids, `jobs_per_epoch` of them
from id 0. The tracer keeps the deposits its steps make, grouped by
epoch, instead of sending them to the server. Once every job of an epoch
is complete and the epoch before it applied, the server asks for the
epoch's sums (or those of a run of complete epochs it merged into one
batch, `epochs` of them) at the hit points it broadcast and the radii the
pixels have now (eqs. 1-5 need a batch gathered at the radii it is
applied to), in up to three rounds (`GATHER_PHASES`):

- "count": how many held deposits lie in their own job's box (the
  pilot's subsample is chosen by a cut that needs the whole epoch's count);
- "pilot": the pilot gather of the radius fit, at the fresh rows;
- "sums": M and Phi per hit point row, plus the deposits and their flux
  (the ledger's totals); the epoch's deposits are then dropped.

Pure: deposits, hit points and requests in, reply fields out. The gather
is the library's (`dosppm_core.sppm.statistics`), socket-free.
"""
from __future__ import annotations

import numpy as np

from dosppm_core.jobs import HitPoints, PhotonDeposits
from dosppm_core.sppm.statistics import gather_sums, pilot_sums
from services.culling import within_own_boxes

HIT_POINT_VERSIONS_KEPT = 2    # the installed set and the next, broadcast before the server installs it
SPARSE_ROW_BYTES, DENSE_ROW_BYTES = 40, 32   # a reached row with its index; any row without


class EpochDeposits:
    """The deposits held per epoch and the hit points broadcast to gather them at."""

    def __init__(self, jobs_per_epoch: int, materials, gather: str = "grid", threads: int = 1,
                 reorder: bool = True, hash_options: dict | None = None):
        if jobs_per_epoch < 1:
            raise ValueError(f"jobs_per_epoch must be >= 1, got {jobs_per_epoch}")
        self.jobs_per_epoch, self.materials = int(jobs_per_epoch), materials
        self.gather, self.threads, self.reorder = gather, int(threads), bool(reorder)
        self.hash_options = hash_options
        self.held: dict[int, list[PhotonDeposits]] = {}
        self.hit_points: dict[int, HitPoints] = {}
        self.dropped: set[int] = set()      # discarded epochs: late deposits of theirs are not kept
        self._culled: dict[int, PhotonDeposits] = {}    # an epoch's deposits in their own boxes
        self.counters = {"deposits_held": 0, "epochs_gathered": 0, "epochs_dropped": 0, "gather_s": 0.0}

    @property
    def rows(self) -> int:
        return sum(len(p) for parts in self.held.values() for p in parts) + \
            sum(len(d) for d in self._culled.values())

    def epoch_of(self, job: np.ndarray) -> np.ndarray:
        return np.asarray(job, np.int64) // self.jobs_per_epoch

    def add(self, deposits: PhotonDeposits) -> None:
        """A step's deposits, kept by epoch (a step's batch is coalesced
        from packages of any jobs, so it may span epochs)."""
        if not len(deposits):
            return
        epochs = self.epoch_of(deposits.job)
        present = np.unique(epochs).tolist()
        for e in present:
            part = deposits if len(present) == 1 else deposits.take(epochs == e)
            if e in self.dropped:
                continue
            self.held.setdefault(e, []).append(part)
            self.counters["deposits_held"] += len(part)

    def clear(self) -> None:
        """Forget every held deposit (a tracer the server welcomed again)."""
        self.held.clear()
        self._culled.clear()

    def set_hit_points(self, version: int, hits: HitPoints) -> None:
        self.hit_points[int(version)] = hits
        for v in sorted(self.hit_points)[:-HIT_POINT_VERSIONS_KEPT]:
            del self.hit_points[v]

    def drop(self, epoch: int) -> None:
        """A discarded epoch: its jobs are re-emitted under new ids, in a later epoch."""
        self.held.pop(epoch, None)
        self._culled.pop(epoch, None)
        self.dropped.add(int(epoch))
        self.counters["epochs_dropped"] += 1

    def reply(self, msg) -> dict:
        """The `epoch_sums` fields answering a `gather` request."""
        e, phase = int(msg.epoch), msg.phase
        own = self._own(e, int(msg.epochs), msg.job_ids, msg.job_boxes)
        out = dict(epoch=e, phase=phase, hits_version=msg.hits_version, deposits=len(own), chosen=0,
                   flux=own.flux.sum(axis=0, dtype=np.float64) if len(own) else np.zeros(3),
                   m=np.zeros(0), phi=np.zeros((0, 3)))
        if phase == "count":
            return out
        hp = self._hits(msg.hits_version)
        if len(msg.rows) and msg.rows[-1] >= len(hp):
            raise ValueError(f"gather: field 'rows' reaches row {int(msg.rows[-1])}, "
                             f"hit points {msg.hits_version} have {len(hp)}")
        if phase == "pilot":
            m, out["chosen"] = pilot_sums([own], hp.take(msg.rows), msg.radius, self.materials,
                                          self.threads, int(msg.most), int(msg.total))
            return dict(out, m=m, phi=np.zeros((len(m), 3)))
        if len(msg.rows) != len(hp):
            raise ValueError(f"gather: field 'rows' has {len(msg.rows)} rows, the sums need all {len(hp)}")
        m, phi = gather_sums([own], hp, msg.radius, self.materials, self.gather, self.threads,
                             self.reorder, self.hash_options)
        self._culled.pop(e, None)       # applied whole by the server once every tracer replies
        self.counters["epochs_gathered"] += 1
        return dict(out, **sparse_sums(np.asarray(m, np.float64), np.asarray(phi, np.float64)))

    def _own(self, epoch: int, count: int, job_ids: np.ndarray, job_boxes: np.ndarray) -> PhotonDeposits:
        """The deposits of epochs `epoch` .. `epoch + count - 1` (one
        gather, merged by the server) inside their own job's box, once: a step
        culls against the union of its packages' boxes, which keeps more;
        culling again here makes what a job adds a function of the job
        alone, as the server's held deposits did (the ledger re-traces it)."""
        if epoch not in self._culled:
            parts = self.take_held(epoch, count)
            deposits = PhotonDeposits.concat(parts) if parts else PhotonDeposits.empty()
            listed = np.isin(deposits.job, job_ids)    # an abandoned job's deposits never count
            deposits = deposits if listed.all() else deposits.take(listed)
            jobs = (job_ids, None, None, job_boxes)
            self._culled[epoch] = within_own_boxes(deposits, jobs) if len(deposits) else deposits
        return self._culled[epoch]

    def take_held(self, epoch: int, count: int = 1) -> list[PhotonDeposits]:
        """The held deposits of `count` epochs from `epoch`, no longer held."""
        return [p for e in range(epoch, epoch + count) for p in self.held.pop(e, [])]

    def _hits(self, version: int) -> HitPoints:
        hp = self.hit_points.get(int(version))
        if hp is None:
            raise ValueError(f"gather: field 'hits_version' names hit points {version} this tracer does not hold "
                             f"(it holds {sorted(self.hit_points)})")
        return hp


def from_welcome(settings: dict, materials, threads: int) -> EpochDeposits | None:
    """The hold a welcome's settings ask for: None when the server gathers."""
    if settings.get("gather_at", "server") != "tracers":
        return None
    return EpochDeposits(int(settings["epoch_jobs"]), materials, settings.get("gather", "grid"), threads,
                         bool(settings.get("reorder", True)))


def sparse_sums(m: np.ndarray, phi: np.ndarray) -> dict:
    """Per hit point sums, as the rows a photon reached with their indices
    when that is smaller than every row without (a sparse image: few hit
    points in the light, or a small epoch)."""
    reached = np.flatnonzero(m > 0)
    if len(reached) * SPARSE_ROW_BYTES < len(m) * DENSE_ROW_BYTES:
        return dict(m=m[reached], phi=phi[reached], rows=reached.astype(np.int64))
    return dict(m=m, phi=phi)


def dense_sums(n: int, m: np.ndarray, phi: np.ndarray, rows: np.ndarray | None) -> tuple:
    """`sparse_sums` back to every one of `n` rows."""
    if rows is None:
        return m, phi
    dm, dphi = np.zeros(n), np.zeros((n, 3))
    dm[rows], dphi[rows] = m, phi
    return dm, dphi
