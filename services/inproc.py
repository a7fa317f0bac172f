"""The whole service in one process: a server and tracers exchanging real
wire messages (encoded, copied to bytes and decoded, as over a socket)
through in-memory queues. The states and messages are those of the
distributed service; only the transport differs. Tests drive clusters
with it deterministically, and it shows what the sockets add."""
from __future__ import annotations

from collections import deque

from dosppm_core.settings import RenderSettings
from services import wire
from services.ledger import Ledger
from services.server.epochs import MOST_MERGED
from services.server.options import ServerOptions
from services.server.state import ServerState
from services.server.statistics import ServerStatistics
from services.tracer.epochs import EpochDeposits
from services.tracer.light import LightHold
from services.tracer.state import SERVER, TracerState
from services.wire import Out


def _over_the_wire(msg_type: str, fields: dict):
    return wire.decode([bytes(f) for f in wire.encode(msg_type, **fields)])


class InProcessCluster:
    def __init__(self, store, settings: RenderSettings, tracers: int = 2, min_photon_jobs: int = 64,
                 queue_target_rays: int = 65_536, step_rays: int = 16_384,
                 memory_bytes: float | None = None, tracer_timeout_s: float = 10.0, tamper=None,
                 gather_at: str = "server", hit_point_stride: int | None = None,
                 batch_growth: int = MOST_MERGED):
        """`tamper(sender, dest, msg)`: the messages to deliver instead of
        `msg` (a faulty transport, for the ledger's negative controls; it
        may hold one back with `later`)."""
        self.settings = settings
        self.server = ServerState(store.header, store.tree, settings, getattr(store, "key", "memory"),
                                  getattr(store, "manifest", None),
                                  ServerOptions(min_photon_jobs=min_photon_jobs, queue_target_rays=queue_target_rays,
                                                min_tracers=tracers, tracer_timeout_s=tracer_timeout_s,
                                                gather_at=gather_at, hit_point_stride=hit_point_stride,
                                                batch_growth=batch_growth))
        self.statistics = ServerStatistics(store.header, settings, threads=settings.threads,
                                           ledger=Ledger(settings, (store.header.camera.width, store.header.camera.height)))
        self.tamper = tamper
        self.store, self.step_rays, self.memory_bytes = store, step_rays, memory_bytes
        self.tracers: dict[str, TracerState] = {}
        self.by_endpoint: dict[str, str] = {}
        self.mail: deque = deque()       # (sender, dest, message)
        self._later: list = []           # (round due, sender, dest, message): a slow link's (`later`)
        self.rounds = 0
        self.dead: set[str] = set()      # killed tracers: they neither send nor receive
        self.messages = 0
        self.wire_bytes = 0
        self.now = 0.0
        for _ in range(tracers):
            self.add_tracer()

    def add_tracer(self) -> str:
        """A tracer joins (at any time): it registers, the server re-assigns
        chunks and sends every tracer the new table."""
        tid = f"t{len(self.tracers)}"
        t = TracerState(f"inproc://{tid}", self.store, self.settings.max_depth,
                        memory_bytes=self.memory_bytes, threads=self.settings.threads,
                        step_rays=self.step_rays, direct=self.settings.direct, clock=lambda: self.now,
                        seed=self.settings.seed, hit_point_stride=self.server.hit_point_stride)
        if self.server.epochs is not None:      # as a tracer's node does on its welcome
            t.hold_epochs(EpochDeposits(self.server.epochs.jobs_per_epoch, self.store.header.materials,
                                        self.settings.gather, self.settings.threads, self.settings.reorder))
        t.hold_light(LightHold())       # as the welcome's `hold_light` tells a tracer's node
        self.tracers[tid], self.by_endpoint[t.endpoint] = t, tid
        reg = _over_the_wire("register", dict(tracer_id=tid, capacity={"cores": 1, "memory_bytes": 0},
                                              endpoint=t.endpoint, has_store=True,
                                              store_key=getattr(self.store, "key", "memory")))
        self._post(SERVER, self.server.on_register(tid, reg, self.now))
        self._deliver()
        return tid

    def kill(self, tid: str) -> None:
        """The tracer stops dead (SIGKILL, a cut cable): nothing more from
        it or to it; the server notices by its missing heartbeats."""
        self.dead.add(tid)

    def _post(self, sender: str, outs) -> None:
        if sender in self.dead:
            return
        for o in outs:
            if o.dest in self.dead or self.by_endpoint.get(o.dest) in self.dead:
                continue
            frames = wire.encode(o.type, **o.fields)
            self.wire_bytes += sum(len(memoryview(f).cast("B")) for f in frames)
            self.messages += 1
            msg = wire.decode([bytes(f) for f in frames])
            for m in (self.tamper(sender, o.dest, msg) if self.tamper else [msg]):
                self.mail.append((sender, o.dest, m))

    def later(self, rounds: int, sender: str, dest: str, msg) -> None:
        """Deliver `msg` `rounds` rounds from now (for a `tamper` that
        plays a slow link)."""
        self._later.append((self.rounds + int(rounds), sender, dest, msg))

    def _deliver(self) -> None:
        while self.mail:
            sender, dest, msg = self.mail.popleft()
            if sender == SERVER:
                self._post(dest, self.tracers[dest].handle(msg))
            elif dest == SERVER:
                self._post(SERVER, self.server.on_message(sender, msg, self.now))
            else:
                tid = self.by_endpoint[dest]
                self._post(tid, self.tracers[tid].handle(msg))

    def _apply_updates(self) -> None:
        while self.server.updates:
            u = self.server.updates.popleft()
            box = self.statistics.apply(u)
            if box is not None:
                self.server.cull_box = box
            self._post(SERVER, self.server.on_applied(u))
            self._deliver()

    def round(self) -> None:
        """One tick of the server (10 ms of cluster time), then one step of
        every live tracer with work; heartbeats every second."""
        self.now += 0.01
        self.rounds += 1
        due = [m for m in self._later if m[0] <= self.rounds]
        self._later = [m for m in self._later if m[0] > self.rounds]
        self.mail.extend(m[1:] for m in due)
        if round(self.now * 100) % 100 == 0:
            for tid in self.tracers:
                self._post(tid, [Out(SERVER, "heartbeat", dict(status={}))])
        self._post(SERVER, self.server.tick(self.now))
        self._deliver()
        for tid, t in self.tracers.items():
            if t.has_work() and tid not in self.dead:
                self._post(tid, t.step())
                self._deliver()
        self._apply_updates()

    def run(self, photons: int | None = None, eye_iterations: int | None = None,
            max_rounds: int = 100_000) -> None:
        """Until `photons` have been emitted or `eye_iterations` completed,
        then drain: every job in flight ends and the last batch is applied."""
        self.render(photons, eye_iterations, max_rounds)
        self.drain(max_rounds)

    def render(self, photons: int | None = None, eye_iterations: int | None = None,
               max_rounds: int = 100_000) -> None:
        for _ in range(max_rounds):
            s = self.server
            if (photons is not None and s.counters["photons_emitted"] >= photons) or \
                    (eye_iterations is not None and s.eye_completed >= eye_iterations):
                break
            self.round()

    def drain(self, max_rounds: int = 100_000) -> None:
        self.server.stop_emitting()
        for _ in range(max_rounds):
            if self.server.drained:
                break
            self.round()
        if not self.server.drained:
            raise RuntimeError(f"cluster did not drain: {len(self.server.jobs)} jobs in flight")
        self.server.finish()
        self._apply_updates()
        self.statistics.end_ledger(self.server.counters["deposits_late"])

    def image(self):
        return self.statistics.image()

    def close(self) -> None:
        for t in self.tracers.values():
            t.close()
