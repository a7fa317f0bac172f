"""`ServerState`'s membership: tracers register, are welcomed (again,
when a welcome or a job message was lost), get the chunk table whenever it
changes (round robin, then rebalanced by their reported work), and are
evicted when silent. A mixin: the tracers, owners and counters are the
state's own (services/server/state.py).
"""
from __future__ import annotations

from services.server.balance import FIRST_REBALANCE_S, REBALANCE_INTERVAL_S, assign_chunks, rebalanced
from services.server.records import TracerInfo
from services.wire import Out

MAX_TRACERS = 1024            # registrations beyond this are refused (memory stays bounded)
HEARTBEAT_INTERVAL_S = 1.0
# A job message an idle tracer has not acknowledged this long after it was
# sent is lost (see `_check_delivery`).
JOB_MESSAGE_LOST_S = 4.0


class MembershipMixin:
    def welcome_fields(self, t: TracerInfo) -> dict:
        s = self.settings
        return dict(tracer_index=t.index, settings={"max_depth": s.max_depth, "seed": s.seed, "direct": s.direct,
                                                    "client_batching": self.client_batching,
                                                    "session": t.session, "hit_point_stride": self.hit_point_stride,
                                                    **self.epoch_settings(), **self.light_settings()},
                    scene=self.header.to_wire(), tree=self.tree.to_wire(), store_key=self.store_key,
                    chunks=[k for k, o in enumerate(self.owners) if t.id in o],
                    manifest=None if t.store_key == self.store_key else self.manifest)

    def on_register(self, tid: str, msg, now: float) -> list[Out]:
        """A tracer joins (or rejoins under the same id): welcome it and
        hand every tracer the new chunk table."""
        t = self.tracers.get(tid)
        cap = msg.capacity
        if t is None and len(self.tracers) >= MAX_TRACERS:
            self.counters["refused"] += 1
            return [Out(tid, "refused", dict(reason=f"the server takes at most {MAX_TRACERS} tracers"))]
        if t is None:
            t = TracerInfo(tid, next(self._indices), msg.endpoint, cap["cores"], cap["memory_bytes"],
                           msg.store_key, now, msg.public_key)
            self.tracers[tid] = t
        else:
            # A tracer registering again has forgotten its queues (it was
            # cut off, or lost our welcome): its share of the work in flight
            # is gone, so every job in flight is discarded and re-emitted.
            t.endpoint, t.store_key, t.last_seen_s = msg.endpoint, msg.store_key, now
            t.public_key = msg.public_key
            t.queued = t.sent_since_report = 0
            self.counters["tracers_rejoined"] += 1
            self.rejoined[tid] = now
            self._discard_jobs_in_flight()
        self._welcomed(t, now)
        self._reassign()
        return [Out(tid, "welcome", self.welcome_fields(t)), *self._peer_tables(), *self._joined_epochs(tid),
                *self._drop_messages()]

    def _reassign(self) -> None:
        ids = [t.id for t in sorted(self.tracers.values(), key=lambda t: t.index)]
        by_id = assign_chunks(self.tree.chunk_count, ids)
        if by_id != self.owners:
            self.owners = by_id
            self.table_version += 1

    def _rebalance(self, now: float) -> list[Out]:
        """Chunks re-assigned by the work the tracers report (balance.py)."""
        if not (self.started and self.emitting):
            return []
        if self._balanced_at is None:
            self._balanced_at = now - REBALANCE_INTERVAL_S + FIRST_REBALANCE_S
        if now - self._balanced_at < REBALANCE_INTERVAL_S:
            return []
        self._balanced_at = now
        tracers = sorted(self.tracers.values(), key=lambda t: t.index)
        new = rebalanced(self.owners, {t.id: t.status for t in tracers}, {t.id: t.cores for t in tracers})
        if new is None:
            return []
        self.owners, self.table_version = new, self.table_version + 1
        self.counters["rebalanced"] += 1
        return self._peer_tables()

    def _peer_tables(self) -> list[Out]:
        peers = [[self.tracers[i].endpoint for i in o] for o in self.owners]
        keys = {t.endpoint: t.public_key for t in self.tracers.values() if t.public_key}
        return [Out(tid, "peers", dict(table_version=self.table_version, peers=peers, keys=keys))
                for tid in self.tracers]

    def _check_welcomed(self, t: TracerInfo, now: float) -> list[Out]:
        """A tracer whose heartbeats do not echo its latest welcome never got
        it (lost with a connection libzmq replaced): it still holds queues
        of its old session. Welcome it again."""
        echoed = t.status.get("session")
        if echoed is None or echoed == t.session or now - t.welcomed_s < 2 * HEARTBEAT_INTERVAL_S:
            return []
        self.counters["welcomes_resent"] += 1
        return self._welcome_again(t, now)

    def _check_delivery(self, t: TracerInfo, now: float) -> list[Out]:
        """Job messages can vanish without an error, queued in a connection
        libzmq replaces after a cut. A tracer counts the job messages it got
        since its welcome; one that is idle while a job message sent to it
        JOB_MESSAGE_LOST_S ago is still unacknowledged lost it. Rather than
        wait for the watchdog, welcome it again at once (its count restarts)
        with the jobs in flight re-emitted. A busy tracer is never suspected:
        it may simply not have read its socket yet."""
        got = t.status.get("jobs_received")
        if got is None:
            return []
        while len(t.unacked) > max(0, t.jobs_sent - int(got)):
            t.unacked.popleft()
        if not t.unacked or now - t.unacked[0] < JOB_MESSAGE_LOST_S or t.status.get("queue", 1):
            return []
        self.counters["job_messages_lost"] += len(t.unacked)
        return self._welcome_again(t, now)

    def _welcome_again(self, t: TracerInfo, now: float) -> list[Out]:
        """A new welcome under a new session (heartbeats of the old one are
        then told apart), with every job in flight re-emitted: the tracer
        forgets its queues when welcomed."""
        self._welcomed(t, now)
        self._discard_jobs_in_flight()
        return [Out(t.id, "welcome", self.welcome_fields(t)), *self._peer_tables(), *self._drop_messages()]

    def _welcomed(self, t: TracerInfo, now: float) -> None:
        t.session += 1
        t.welcomed_s = now
        t.jobs_sent = 0
        t.unacked.clear()

    def _ready_to_start(self, now: float) -> bool:
        if len(self.tracers) >= self.min_tracers:
            return True
        if self._waiting_since is None:
            self._waiting_since = now
        timeout = self.min_tracers_timeout_s
        if timeout is None or not self.tracers or now - self._waiting_since < timeout:
            return False
        self.start_note = (f"starting with {len(self.tracers)} of {self.min_tracers} tracers: "
                           f"waited {timeout:g} s (--min-tracers-timeout)")
        return True

    def waiting_for(self) -> dict | None:
        """What keeps the render from running, for the status page and the
        server's log line: tracers still to register, or chunks no tracer
        holds (after an eviction); None while it runs."""
        if not self.started:
            return {"tracers": self.min_tracers - len(self.tracers), "registered": len(self.tracers),
                    "min_tracers": self.min_tracers}
        unowned = [k for k, o in enumerate(self.owners) if not o]
        return {"chunk_owners": unowned} if unowned else None

    def _evict_silent(self, now: float) -> list[Out]:
        """Tracers silent for `tracer_timeout_s` (killed, hung or cut off)
        are dropped; see `evict`."""
        out = []
        for t in [t for t in self.tracers.values() if now - t.last_seen_s > self.tracer_timeout_s]:
            out += self.evict(t.id, f"silent for {now - t.last_seen_s:.1f} s")
        return out

    def _all_idle(self, now: float) -> bool:
        return bool(self.tracers) and all(
            now - t.status_s < 2 * HEARTBEAT_INTERVAL_S and t.status.get("queue", 1) == 0
            and t.status.get("outbox_rays", 1) == 0 for t in self.tracers.values())

    def evict(self, tid: str, reason: str) -> list[Out]:
        """Drop tracer `tid`: its chunks go to the live tracers (new peer
        tables), and every job in flight is discarded whole and re-emitted.
        Any of them may have had paths queued at or travelling to the lost
        tracer, and the server cannot know which, so none of their deposits
        or hit points count; photon jobs are re-emitted with the same random
        streams (the same photons, a new job id) and an eye iteration in
        flight starts over. Late results of discarded jobs are stale."""
        self.tracers.pop(tid)
        self.evicted.append({"id": tid, "reason": reason})
        self.counters["tracers_evicted"] += 1
        self._reassign()
        self._discard_jobs_in_flight()
        return self._peer_tables() + self._drop_messages()

    def shutdown_messages(self, reason: str) -> list[Out]:
        return [Out(tid, "shutdown", dict(reason=reason)) for tid in self.tracers]
