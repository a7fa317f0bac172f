"""`ServerState`'s part in the gather at the tracers (`--gather-at
tracers`; services/server/epochs.py has the epochs, docs/how-it-works.md
"The gather at the tracers" the derivation). A mixin: the state's job
records, tracers and update queue are its own; this adds the steps an
epoch goes through:

    photon jobs complete -> epoch due -> Update("gather", "start")
    -> statistics: the first round's request -> `on_applied` asks every
    live tracer -> their `epoch_sums` -> Update("gather", <round>) ...
    -> the "sums" round's answers -> Update("epoch") -> applied.

Hit points installed by the statistics are broadcast (`on_applied` of a
"hits" update), and a new eye iteration's hit points wait while an epoch
is gathered, so every round of an epoch reads one set of hit points.
"""
from __future__ import annotations

from collections import deque

from services.server.epochs import Epochs, jobs_per_epoch, total
from services.server.records import Update
from services.wire import Out

NEXT_STAGE = {"count": "count", "pilot": "pilot"}    # a round answered -> the "gather" stage after it


class EpochStateMixin:
    epochs: Epochs | None = None

    def _init_epochs(self, gather_at: str, tracers: int, batch_growth: int, held_bytes: float) -> None:
        if gather_at not in ("server", "tracers"):
            raise ValueError(f"gather_at must be 'server' or 'tracers', got {gather_at!r}")
        self.gather_at = gather_at
        self._hits_waiting: deque = deque()
        self._hit_points_out: dict | None = None     # the last broadcast, for tracers joining later
        if gather_at == "tracers":
            s = self.settings
            per = jobs_per_epoch(s.photon_batch, s.photons_per_job, max(1, tracers), self.n_pixels)
            self.epochs = Epochs(per, most_merged=batch_growth, held_bytes=held_bytes)

    def epoch_settings(self) -> dict:
        """What a tracer's welcome says about epochs (none: it sends its deposits)."""
        if self.epochs is None:
            return {"gather_at": "server"}
        s = self.settings
        return {"gather_at": "tracers", "epoch_jobs": self.epochs.jobs_per_epoch, "gather": s.gather,
                "reorder": s.reorder}

    def _joined_epochs(self, tid: str) -> list[Out]:
        """A tracer joining gets the installed hit points."""
        return [] if self._hit_points_out is None else [Out(tid, "hit_points", self._hit_points_out)]

    def _eye_update(self, update: Update) -> None:
        """A complete eye iteration's hit points: they wait while an epoch is gathered."""
        if self.epochs is not None and self.epochs.asking:
            self._hits_waiting.append(update)
        else:
            self.updates.append(update)

    def _maybe_gather(self) -> None:
        e = self.epochs.due(self.next_job, self.emitting)
        if e is not None:
            self.updates.append(Update("gather", epoch=e, stage="start"))

    def on_applied(self, update: Update) -> list[Out]:
        """What the shell sends once the statistics applied `update`."""
        if self.epochs is None:
            return []
        if update.kind == "hits" and update.installed is not None:
            self._hit_points_out = dict(hits_version=update.eye_iteration, hits=update.installed)
            return [Out(tid, "hit_points", self._hit_points_out) for tid in self.tracers]
        if update.kind == "gather":
            e = update.epoch
            if update.request is None or self.epochs.open.get(e.index) is not e:
                return []                  # discarded meanwhile
            self.epochs.ask(e, update.request["phase"], self.tracers, self._now, len(update.request["rows"]))
            return [Out(tid, "gather", update.request) for tid in self.tracers]
        if update.kind == "epoch":
            self.epochs.applied(update.epoch, update.sums["deposits"], self._now)
            while self._hits_waiting:
                self.updates.append(self._hits_waiting.popleft())
            self._maybe_gather()
        return []

    def _on_epoch_sums(self, tid: str, msg) -> list[Out]:
        if self.epochs is None:
            return [Out(tid, "error", dict(reason="epoch_sums: this server gathers itself", about="epoch_sums"))]
        try:
            e = self.epochs.answer(tid, msg)
        except ValueError as err:
            return [Out(tid, "error", dict(reason=str(err), about="epoch_sums"))]
        if e is None:
            return []
        sums = total(e.sums, e.rows)
        if e.phase in NEXT_STAGE:
            self.updates.append(Update("gather", epoch=e, stage=NEXT_STAGE[e.phase], sums=sums))
            return []
        ids, keys, paths, boxes = e.columns()
        e.phase = "applying"
        photons = int(paths.sum())
        self.updates.append(Update("epoch", epoch=e, sums=sums, photons_emitted=photons, jobs=(keys, paths, boxes)))
        c = self.counters
        c["photons_committed"] += photons
        c["deposits_received"] += sums["deposits"]
        return []

    def _discard_epochs(self) -> None:
        """A tracer lost or restarted: every epoch not handed to the
        statistics is discarded whole, its held deposits dropped at the
        tracers, and its complete jobs made again (the same random streams,
        new ids past every discarded epoch); jobs in flight are re-emitted
        by the caller, under ids past them too."""
        lost = self.epochs.discard_unapplied()
        if not lost:
            return
        for e in lost:
            e.phase = "discarded"
        self.next_job = max(self.next_job, self.epochs.first_id_after(max(e.last for e in lost)))
        again, c = [], self.counters
        for e in lost:
            for j, (key, paths, _box) in sorted(e.jobs.items()):
                again.append(self._new_job("photon", paths, rng_key=key))
                # Complete, but never to be applied: counted discarded, not
                # completed (completed = committed once the render drains).
                c["photons_discarded"] += paths
                c["photons_completed"] -= paths
                c["photon_jobs_completed"] -= 1
                c["jobs_discarded"] += 1
        self._photon_pending.extendleft(reversed(again))
        pending = [j for j in self._photon_pending if self.epochs.of(j) in self.epochs.discarded]
        for j in pending:          # made, not sent: ids of a discarded epoch are never used again
            job = self.jobs.pop(j)
            self.photon_jobs_in_flight -= 1
            again.append(self._new_job("photon", job.paths, rng_key=job.rng_key))
        if pending:
            dead = set(pending)
            self._photon_pending = deque([j for j in self._photon_pending if j not in dead])
            self._photon_pending.extend(again[-len(pending):])
        self._drops = [i for e in lost for i in e.indices]

    def _drop_messages(self) -> list[Out]:
        drops, self._drops = getattr(self, "_drops", []), []
        return [Out(tid, "drop_epoch", dict(epoch=e)) for e in drops for tid in self.tracers]

    def epochs_drain_s(self) -> float:
        """Seconds the epochs not yet applied take to gather (0 gathering at the server)."""
        return 0.0 if self.epochs is None else self.epochs.drain_s()

    @property
    def epochs_drained(self) -> bool:
        return self.epochs is None or not self.epochs.unapplied
