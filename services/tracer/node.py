"""The tracer process: `TracerState` behind ZeroMQ sockets (`dosppm worker`).

It registers with the server (DEALER, its tracer id as routing identity),
receives its chunks and the peer table, and loops: take whatever arrived
(server jobs on the DEALER, portal packages from peers on its own ROUTER),
trace one step, send the results to the server and the portal packages to
the peers serving the next chunks. Chunks come from the chunk store at
`--store` when it is the server's (same key), otherwise they are fetched
from the server by id and checked against the manifest's SHA-256.
"""
from __future__ import annotations

import logging
import os
import signal
import socket as pysocket
import threading
import time
import uuid
from dataclasses import dataclass

from dosppm_core.chunks.store import ChunkStore, StoreError
from dosppm_core.kernels import use_threads
from dosppm_core.scene.model import SceneHeader
from services import transport, wire
from services.tracer.epochs import from_welcome
from services.tracer.light import LightHold
from services.tracer.merge import MergedResults, mergeable
from services.tracer.fetch import FetchedStore
from services.tracer.state import SERVER, STEP_RAYS, TracerState

log = logging.getLogger("dosppm.tracer")
HEARTBEAT_INTERVAL_S = 1.0
SERVER_TIMEOUT_S = 60.0       # default --retry: no word from the server this long, give up
SERVER_SILENT_S = 5.0         # the server heartbeats every second: after this, register again


class TracerError(RuntimeError):
    """A one-line reason the tracer stopped (refused, server gone)."""


def reachable_address(server_url: str) -> str:
    """This host's address on the route to the server (a UDP 'connect'
    sends nothing): what other tracers on that network can reach."""
    host, _, port = server_url.split("://", 1)[-1].rpartition(":")
    with pysocket.socket(pysocket.AF_INET, pysocket.SOCK_DGRAM) as s:
        s.connect((pysocket.gethostbyname(host.strip("[]")), int(port) if port.isdigit() else 9))
        return s.getsockname()[0]


def _chunk_list(chunks) -> str:
    return ", ".join(map(str, chunks)) if chunks else "none yet"


def default_tracer_id() -> str:
    return f"{pysocket.gethostname()}-{os.getpid()}-{uuid.uuid4().hex[:6]}"


@dataclass
class TracerOptions:
    """The flags of `dosppm worker`: the server to join, where peers reach
    this tracer, its store, cache and memory, and its CURVE keys."""
    server: str
    bind: str = "tcp://127.0.0.1:*"
    advertise: str | None = None
    store: str | None = None
    cache_dir: str | None = None
    memory_bytes: float | None = None
    queue_memory_bytes: float | None = None
    threads: int = 1
    tracer_id: str | None = None
    connect_timeout_s: float = SERVER_TIMEOUT_S     # --retry
    curve_secret: str | None = None
    curve_server_key: str | None = None
    curve_clients: str | None = None


class TracerProcess:
    state_class = TracerState   # the replay harness (harness/replay.py) swaps it

    def __init__(self, options: TracerOptions, context: transport.Context | None = None, say=None):
        """`say` prints a line for the user: the server joined, rejoins."""
        o = self.options = options
        self.say = say or (lambda *parts: None)
        self.server_url, self.bind, self.advertise = o.server, o.bind, o.advertise
        self.store_path, self.cache_dir = o.store, o.cache_dir
        self.memory_bytes, self.threads = o.memory_bytes, o.threads
        self.queue_memory_bytes = o.queue_memory_bytes
        self.tracer_id = o.tracer_id or default_tracer_id()
        self.connect_timeout_s = o.connect_timeout_s
        self.curve = (o.curve_secret, o.curve_server_key, o.curve_clients) if o.curve_secret else None
        if self.curve and not (o.curve_server_key and o.curve_clients):
            raise TracerError("--curve-secret needs --curve-server-key and --curve-clients")
        self.peer_keys: dict[str, str] = {}
        self.public_key: str | None = None
        self.auth = None
        self.ctx = context             # None: the process's shared one
        self.state: TracerState | None = None
        self.peers: dict[str, transport.Socket] = {}
        self.outbox: list = []        # (endpoint, frames) waiting for a full peer pipe
        self.merged = MergedResults()   # accounting-only results, sent together (merge.py)
        self.stopped: str | None = None
        self.session = None            # the registration the server last welcomed
        self.jobs_received = 0         # job messages since that welcome (acknowledged in heartbeats)
        self._rejoining = False
        self._backoff, self._next_rejoin = 0.0, 0.0
        self._last_register = 0.0
        self.bytes_to_server = self.bytes_to_peers = 0
        self._outbox_rays = 0
        # Where the loop's time goes (status page, issue 17): waiting for
        # work, decoding what arrived, and tracing plus sending.
        self.loop_s = {"idle_s": 0.0, "receive_s": 0.0, "step_send_s": 0.0}
        self._poller: transport.Poller | None = None

    # -- sockets -------------------------------------------------------------------
    def _open(self) -> None:
        try:
            self._open_sockets()
        except transport.CurveError as e:   # a key file or folder the user named: one line
            raise TracerError(str(e)) from None

    def _open_sockets(self) -> None:
        self.dealer = self._connect_server()
        self.router = transport.router(self.ctx)
        if self.curve:
            # To peers as a CURVE server that admits only the listed
            # tracers' keys (to the server as a client: _connect_server).
            secret, _server_key, clients = self.curve
            self.auth = transport.start_authenticator(clients, self.ctx)
            self.public_key = transport.curve_server(self.router, secret).decode()
        bound = self.router.bind(self.bind)
        if self.advertise:   # bound to 0.0.0.0: peers need a reachable address
            host = reachable_address(self.server_url) if self.advertise == "auto" else self.advertise
            bound = f"tcp://{host}:{bound.rsplit(':', 1)[1]}"
        self.endpoint = bound

    def _connect_server(self) -> transport.Socket:
        """A DEALER to the server under this tracer's identity."""
        dealer = transport.dealer(self.tracer_id, self.ctx)
        if self.curve:
            secret, server_key, _clients = self.curve
            transport.curve_client(dealer, secret, transport.load_keys(server_key)[0])
        dealer.connect(self.server_url)
        return dealer

    def _replace_connection(self) -> None:
        """The server went silent: drop the connection and open a new one.
        The old one may be a TCP connection a network cut left half dead;
        closing it tells the server (once packets flow) to let go of this
        identity, which its ROUTER otherwise keeps, ignoring the new
        connection, until its heartbeat times out. What was queued in it
        belongs to jobs the server re-emits when this tracer registers."""
        old, self.dealer = self.dealer, self._connect_server()
        if self._poller is not None:
            self._poller.unregister(old)
            self._poller.register(self.dealer)
        old.close(linger_ms=0)

    def _peer(self, endpoint: str) -> transport.Socket:
        s = self.peers.get(endpoint)
        if s is None:
            s = transport.dealer(self.tracer_id, self.ctx)
            if self.curve:
                if endpoint not in self.peer_keys:
                    raise TracerError(f"no CURVE key for peer {endpoint} in the server's table")
                transport.curve_client(s, self.curve[0], self.peer_keys[endpoint].encode())
            s.connect(endpoint)
            self.peers[endpoint] = s
        return s

    # -- registration ----------------------------------------------------------------
    def _register(self):
        self.dealer.send(self._register_frames(self._local_store_key()))
        # The DEALER queues the register until the server is up (libzmq
        # reconnects with its own backoff), so waiting is all it takes.
        timeout_s = self.connect_timeout_s
        for msg in self._server_messages(time.monotonic() + timeout_s):
            if msg.type == "refused":
                raise TracerError(f"server refused this tracer: {msg.reason}")
            if msg.type == "welcome":
                return msg
            if msg.type == "error":
                raise TracerError(f"server: {msg.reason}")
        raise TracerError(f"no answer from server {self.server_url} within {timeout_s:.0f} s")

    def _register_frames(self, store_key: str | None) -> list:
        return wire.encode("register", tracer_id=self.tracer_id, endpoint=self.endpoint,
                           capacity={"cores": self.threads, "memory_bytes": int(self.memory_bytes or 0)},
                           has_store=store_key is not None, store_key=store_key,
                           public_key=self.public_key)

    def _server_messages(self, deadline: float):
        """Decoded messages from the server until `deadline` (bad ones are
        answered and skipped by `recv_or_reply`)."""
        while time.monotonic() < deadline:
            if self.dealer.poll(200):
                got = self.dealer.recv_or_reply()
                if got is not None:
                    yield got[1]

    def _local_store_key(self) -> str | None:
        if not self.store_path:
            return None
        try:
            return ChunkStore.open(self.store_path).key
        except StoreError as e:
            log.warning("ignoring --store: %s", e)
            return None

    def _provider(self, welcome):
        if self.store_path and welcome.manifest is None:
            store = ChunkStore.open(self.store_path)
            if store.key == welcome.store_key:
                return store
        if welcome.manifest is None:
            raise TracerError("server sent no manifest and this tracer has no matching store")
        cache = self.cache_dir or os.path.join(os.path.expanduser("~"), ".cache", "dosppm", "fetched")
        return FetchedStore(welcome.manifest, os.path.join(cache, welcome.store_key), self._request_chunk)

    # -- chunk fetching (LAN nodes without the store) ------------------------------------
    def _request_chunk(self, chunk: int, timeout_s: float = 600.0) -> list:
        """Ask the server for chunk `chunk` by id and wait for its parts;
        other messages arriving meanwhile are handled as usual."""
        self.dealer.send(wire.encode("chunk_request", chunk=chunk))
        parts = []
        for msg in self._server_messages(time.monotonic() + timeout_s):
            if msg.type == "chunk_data" and msg.chunk == chunk:
                parts.append(msg)
                if len(parts) == msg.parts:
                    return parts
            elif msg.type == "error" and msg.about == "chunk_request":
                raise TracerError(f"server: {msg.reason}")
            else:
                self._pending_server.append(msg)
        raise TracerError(f"chunk {chunk} did not arrive within {timeout_s:.0f} s")

    # -- the loop ----------------------------------------------------------------------
    def run(self) -> str:
        """Serve until the server says shutdown (or SIGTERM/SIGINT arrive);
        returns the reason."""
        restore = self._stop_on_signals()
        try:
            return self._run()
        finally:
            restore()

    def _stop_on_signals(self):
        if threading.current_thread() is not threading.main_thread():
            return lambda: None

        def stop(signum, frame):
            self.stopped = f"stopped by signal {signum}"
        old = {s: signal.signal(s, stop) for s in (signal.SIGINT, signal.SIGTERM)}
        return lambda: [signal.signal(s, h) for s, h in old.items()]

    def _run(self) -> str:
        self._open()
        self._pending_server: list = []
        self._last_heard = time.monotonic()
        try:
            welcome = self._register()
            provider = self._provider(welcome)
            batching = welcome.settings.get("client_batching", True)
            self.session = welcome.settings.get("session")
            self.state = self.state_class(self.endpoint, provider, welcome.settings["max_depth"],
                                     memory_bytes=self.memory_bytes, threads=self.threads,
                                     step_rays=STEP_RAYS if batching else 0,
                                     direct=welcome.settings.get("direct", "nee"),
                                     queue_memory_bytes=self.queue_memory_bytes,
                                     seed=welcome.settings["seed"],
                                     header=SceneHeader.from_wire(welcome.scene),
                                     hit_point_stride=welcome.settings.get("hit_point_stride", 1))
            epochs = from_welcome(welcome.settings, provider.header.materials, self.threads)
            if epochs is not None:
                self.state.hold_epochs(epochs)
            self.state.hold_light(LightHold() if welcome.settings.get("hold_light") else None)
            log.info("tracer %s joined as %d at %s, chunks %s", self.tracer_id, welcome.tracer_index,
                     self.endpoint, welcome.chunks)
            self.say(f"tracer {self.tracer_id}: registered with server {self.server_url} as tracer "
                     f"{welcome.tracer_index}, chunks {_chunk_list(welcome.chunks)}, portals at {self.endpoint}")
            self._loop()
        finally:
            self._close()
        return self.stopped or ""

    def _loop(self) -> None:
        # The bounce kernels keep to --threads, as Embree's tracing does.
        # numba's default is every core: beside another tracer and the
        # server, a kernel's second OpenMP thread waits for a core while
        # this one sleeps at the barrier.
        use_threads(self.threads)
        self._poller = poller = transport.Poller(self.dealer, self.router)
        last_beat = self._last_heard = time.monotonic()
        while self.stopped is None:
            busy = self.state.has_work() or bool(self.outbox)
            t0 = time.monotonic()
            events = poller.poll(0 if busy else 50)
            now = time.monotonic()
            self.loop_s["idle_s"] += now - t0
            if self.dealer in events or self._pending_server:
                self._last_heard = now
            self._drain_server(self.dealer in events)
            if self.router in events:
                self._drain_peers()
            t1 = time.monotonic()
            self.loop_s["receive_s"] += t1 - now
            if self.state.has_work():
                self._send(self.state.step())
            if not self.state.has_work() or self.merged.due(time.monotonic()):
                self._send_merged()
            self._flush_outbox()
            self.loop_s["step_send_s"] += time.monotonic() - t1
            if now - last_beat >= HEARTBEAT_INTERVAL_S:
                last_beat = now
                # Read what arrived during a long step first: the heartbeat
                # acknowledges job messages (`jobs_received`), and one that
                # is only unread must not look lost.
                if self.dealer.poll(0):
                    self._last_heard = now
                    self._drain_server(True)
                self._to_server(wire.encode("heartbeat", status=self._status()), disposable=True)
            if now - self._last_heard > SERVER_SILENT_S:
                self._reconnect(now, now - self._last_heard)

    def _status(self) -> dict:
        s = self.state.status()
        s.update(session=self.session, jobs_received=self.jobs_received, outbox=len(self.outbox),
                 outbox_rays=self._outbox_rays, **{k: round(v, 3) for k, v in self.loop_s.items()},
                 cpu_s=round(time.process_time(), 3),
                 bytes_to_server=self.bytes_to_server, bytes_to_peers=self.bytes_to_peers)
        return s

    def _drain_server(self, ready: bool) -> None:
        msgs, self._pending_server = self._pending_server, []
        if ready:
            msgs.extend(msg for _prefix, msg in self.dealer.drain())
        for msg in msgs:
            if msg.type == "shutdown":
                self.stopped = msg.reason or "shutdown"
            elif msg.type == "error" and "is not registered" in msg.reason:
                self._rejoin()
            elif msg.type == "welcome":
                # Back after the server dropped us (we were hung or cut off)
                # or restarted: what we still hold belongs to jobs it has
                # discarded or never knew.
                self.session = msg.settings.get("session")
                self.jobs_received = 0
                self.merged.clear()       # of jobs the server discarded or never knew
                self.state.reset()
                self.state.header = SceneHeader.from_wire(msg.scene)     # the eye rays' camera
                self.state.hit_point_stride = int(msg.settings.get("hit_point_stride", 1))
                # A server restarted from a checkpoint may cut epochs otherwise.
                self.state.hold_epochs(from_welcome(msg.settings, self.state.provider.header.materials,
                                                    self.threads))
                self.state.hold_light(LightHold() if msg.settings.get("hold_light") else None)
                self._rejoining, self._backoff = False, 0.0
                log.info("rejoined the server as tracer %d", msg.tracer_index)
                self.say(f"tracer {self.tracer_id}: rejoined server {self.server_url} as tracer "
                         f"{msg.tracer_index}, chunks {_chunk_list(msg.chunks)}")
            elif msg.type in ("error", "refused"):
                log.warning("server says: %s", msg.reason)
            else:
                if msg.type == "peers":
                    self.peer_keys.update(msg.keys)
                elif msg.type in wire.JOB_MESSAGES:
                    self.jobs_received += 1
                self._send(self.state.handle(msg))
                if msg.type == "peers":
                    log.info("peer table %d: this tracer serves chunks %s", msg.table_version,
                             self.state.chunks)

    def _reconnect(self, now: float, silent_s: float) -> None:
        """The server went quiet (restarting, or the link is down): open a
        new connection and register again, with backoff (1, 2, 4, ... 16 s),
        and give up only after `connect_timeout_s` of silence."""
        if silent_s > self.connect_timeout_s:
            raise TracerError(f"server {self.server_url} silent for {silent_s:.0f} s")
        if now < self._next_rejoin:
            return
        self._backoff = min(2 * self._backoff, 16.0) if self._backoff else 1.0
        self._next_rejoin = now + self._backoff
        self._rejoining = False
        self._replace_connection()
        self._rejoin()

    def _rejoin(self) -> None:
        """The server no longer knows us (it evicted us while we were
        silent): register again, and again at most once a second while it
        keeps saying so (a register or its welcome can be lost with a
        connection libzmq replaces), until welcomed."""
        now = time.monotonic()
        if self._rejoining and now - self._last_register < 1.0:
            return
        self._rejoining, self._last_register = True, now
        log.warning("no server, or it dropped this tracer: registering again")
        self._to_server(self._register_frames(self.state.provider_key), disposable=True)

    def _drain_peers(self) -> None:
        for prefix, msg in self.router.drain(accept={"portal_rays"}):
            try:
                self._send(self.state.handle(msg))
            except ValueError as e:      # a range only this tracer can check (chunk id)
                log.warning("bad package from %r: %s", prefix[0], e)
                try:
                    self.router.send(wire.encode("error", reason=f"portal_rays: {e}", about="portal_rays"),
                                     prefix, block=False)
                except transport.TransportError:   # the sender is gone or not reading: the log line stands
                    pass

    def _send(self, outs) -> None:
        for o in outs:
            if o.type == "results":
                # Rays waiting for a slow peer count as queued here: the
                # server's credit then stops this tracer's share of new jobs
                # instead of its outbox growing without bound.
                o.fields["queued"] += self._outbox_rays
                if mergeable(o.fields):       # sent with the next ones (merge.py)
                    self.merged.add(o.fields, time.monotonic())
                    continue
            if o.dest == SERVER:
                self._send_merged()           # what came before goes first
                self._to_server_counted(wire.encode(o.type, **o.fields))
                continue
            rays = len(o.fields["shadows" if o.fields["kind"] == "shadow" else "batch"])
            self.outbox.append((o.dest, wire.encode(o.type, **o.fields), rays))
            self._outbox_rays += rays
        self._flush_outbox()

    def _send_merged(self) -> None:
        for fields in self.merged.take():
            self._to_server_counted(wire.encode("results", **fields))

    def _to_server_counted(self, frames) -> None:
        self._to_server(frames)
        self.bytes_to_server += sum(memoryview(f).nbytes for f in frames)

    def _to_server(self, frames, disposable: bool = False) -> None:
        """Heartbeats and registers are dropped when the pipe to the server
        is full (it is down; another goes out soon). Results wait until the
        server has been silent `connect_timeout_s`, the same give-up time
        as `_reconnect`'s: counted from when it was last heard, not from
        this send, or a send begun late in a cut would double --retry."""
        if disposable:
            try:
                self.dealer.send(frames, block=False)
            except transport.WouldBlock:
                pass
            return
        deadline = self._last_heard + self.connect_timeout_s
        while True:
            try:
                self.dealer.send(frames, block=False)
                return
            except transport.WouldBlock:
                if time.monotonic() > deadline or self.stopped is not None:
                    raise TracerError(f"server {self.server_url} took no results for "
                                      f"{self.connect_timeout_s:.0f} s") from None
                time.sleep(0.05)

    def _flush_outbox(self) -> None:
        """Peers get packages without blocking: two tracers blocked sending
        to each other would deadlock. What does not fit waits here."""
        waiting = []
        for dest, frames, rays in self.outbox:
            try:
                self._peer(dest).send(frames, block=False)
            except transport.WouldBlock:
                waiting.append((dest, frames, rays))
                continue
            self._outbox_rays -= rays
            self.bytes_to_peers += sum(memoryview(f).nbytes for f in frames)
        self.outbox = waiting

    def _close(self) -> None:
        if self.state is not None:
            self.state.close()
        for s in (*self.peers.values(), self.dealer, self.router):
            s.close()
        if self.auth is not None:
            self.auth.stop()
