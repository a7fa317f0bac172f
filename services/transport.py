"""The transport of the distributed service (DOSPPM, Günther & Grosch §3.1
"Network"): ZeroMQ sockets that carry the wire's messages, and CURVE keys.
The only module of the project that imports zmq; `services.wire` is the
codec it sends and receives with.

API
---
    router(context=None), dealer(identity, context=None) -> Socket
    Socket: bind(address) -> endpoint, connect(address), send(frames, prefix=(), block=True),
            recv(accept=None, block=True) -> (prefix, Message), recv_or_reply(...),
            drain(accept=None, limit=None) -> (prefix, Message) of every waiting message,
            poll(timeout_ms) -> bool, close(linger_ms=LINGER_MS)
    Poller(*sockets): register, unregister, poll(timeout_ms) -> set of ready Sockets
    TransportError(RuntimeError); WouldBlock, Unreachable, CurveError (its kinds)
    make_keys(directory, name), load_keys(path), curve_server(socket, secret_file),
    curve_client(socket, secret_file, server_public), start_authenticator(clients_dir, context=None)

Sockets, envelopes and back-pressure
------------------------------------
The server binds a ROUTER; each tracer connects a DEALER to it, with its
tracer_id as ZMQ routing id (a reconnect keeps its identity). Each tracer
also binds a ROUTER at its `endpoint` for peer traffic, and connects one
DEALER per peer. Envelope convention: DEALERs send no empty delimiter, so a
ROUTER receives exactly one identity frame before the message (`recv`
returns it as the prefix; send it back in front of a reply).

Nothing is dropped silently:
- every ROUTER sets ROUTER_MANDATORY, so sending to an unknown or
  disconnected identity raises `Unreachable` instead of vanishing, and a
  full queue raises `WouldBlock` (non-blocking send) instead of dropping;
- high-water marks are HWM_MESSAGES messages, not the default 1000: a
  message can be a ray batch of tens of MB (56 B per ray: an eye job's
  tile, a tracer's coalesced portal packages and results; a photon job
  is a few hundred bytes, its photons made by the tracer);
- memory stays bounded by credit, not by queue: the server sends photon
  jobs to a tracer only while the rays it last reported queued, plus the
  rays sent to it since, stay under a ray credit (`ServerState.credit`:
  `queue_target_rays`, shared out so that the rays queued at all tracers
  together stay under TOTAL_CREDIT_RAYS). Jobs past the credit wait at the
  server, not yet emitted, so a slow tracer slows its own share instead of
  growing buffers;
- peers send portal packages non-blocking and keep what does not fit in
  an outbox while they keep receiving: two tracers blocked sending to each
  other would deadlock. The rays waiting in a tracer's outbox count as
  queued in its results, so the server's credit stops its photon jobs too;
- a bad message is answered with `error` (or `refused`, for a register in
  another version) and logged (`recv_or_reply`); an `error` or `refused` is
  never answered, so two confused peers cannot ping-pong.
Frames given to `send` are copied into zmq's buffers (see `Socket.send`).
Received arrays are views of zmq's frames (`wire.decode`).

Liveness is the roles' business: hung or cut-off processes are found by
their `heartbeat` messages, and a tracer that hears nothing from the server
opens a new connection under its own identity, which a ROUTER hands over
to at once (ZMQ_ROUTER_HANDOVER; the old connection and what was queued in
it are dropped, which the job-message acknowledgements recover). The
kernel's keepalive closes idle connections to dead hosts. Not libzmq's own
heartbeats (ZMQ_HEARTBEAT_*): a heartbeat timeout on a connection whose
input is stopped by RCVHWM makes libzmq 4.3 abort the process
(`!_io_error`, libzmq issues 3937 and 4364; it killed the server of
tests/test_load.py). Not a retransmission limit (ZMQ_TCP_MAXRT) either:
Linux applies it to zero-window probes, so it cut the connections of
tracers that were only slow to read (16 tracers on 2 cores).

Errors
------
Every zmq failure leaves this module as a `TransportError` with zmq's one
line: `WouldBlock` (a non-blocking send found the queue full, or nothing
waits to be received), `Unreachable` (ROUTER_MANDATORY: no such peer), and
`CurveError` (a key file or key directory that cannot be used). A bad
message is a `wire.WireError`, as from `wire.decode`.

CURVE (encryption and authentication on a LAN)
----------------------------------------------
Keys are ZeroMQ certificate files (`dosppm keys`): NAME.key_secret (mode
0600, on that host only) and NAME.key (public). A CURVE server socket admits
only the clients whose public keys are in the directory given to
`start_authenticator` (ZeroMQ's ZAP handler, on a thread).
"""
from __future__ import annotations

import logging
import os

import zmq
import zmq.utils.monitor
import zmq.auth
from zmq.auth.thread import ThreadAuthenticator

from services.wire import MAX_FRAME_BYTES, Message, WireError, decode, error_reply

# -- policy ---------------------------------------------------------------------
HWM_MESSAGES = 16                # SNDHWM and RCVHWM, per socket and peer
LINGER_MS = 2000                 # a closing socket still delivers its last results
TCP_KEEPALIVE_IDLE_S = 2         # the kernel closes idle connections to dead
TCP_KEEPALIVE_INTVL_S = 1        # hosts after 2 + 8 x 1 s of probes (module doc)
TCP_KEEPALIVE_CNT = 8

Context = zmq.Context

log = logging.getLogger("dosppm.transport")


class TransportError(RuntimeError):
    """A socket operation failed; zmq's reason in one line."""


class WouldBlock(TransportError):
    """A non-blocking send found the peer's queue full (nothing was sent),
    or a non-blocking receive found nothing waiting."""


class Unreachable(TransportError):
    """A ROUTER was asked to send to an identity it does not know (never
    connected, or disconnected): ROUTER_MANDATORY's EHOSTUNREACH."""


class CurveError(TransportError):
    """A CURVE key file or key directory that cannot be used."""


def _translated(e: zmq.ZMQError) -> TransportError:
    if isinstance(e, zmq.Again):
        return WouldBlock(str(e))
    if e.errno == zmq.EHOSTUNREACH:
        return Unreachable(str(e))
    return TransportError(str(e))


# -- sockets --------------------------------------------------------------------
class Socket:
    """A ROUTER or DEALER under the policy above, sending and receiving the
    wire's messages."""

    def __init__(self, raw: zmq.Socket):
        self._raw = raw
        self.is_router = raw.type == zmq.ROUTER
        # The frames of every message received, bad ones too: the cost per
        # photon on the wire (issue 32). Not the envelope: zmq's own.
        self.bytes_in = 0
        self.bytes_in_by_type: dict[str, int] = {}     # the same, by message type

    def bind(self, address: str) -> str:
        """Bind (after any CURVE set-up: zmq reads it here); returns the
        endpoint actually bound, a `*` port resolved."""
        try:
            self._raw.bind(address)
            return self._raw.getsockopt(zmq.LAST_ENDPOINT).decode()
        except zmq.ZMQError as e:
            raise _translated(e) from None

    def connect(self, address: str) -> None:
        try:
            self._raw.connect(address)
        except zmq.ZMQError as e:
            raise _translated(e) from None

    def send(self, frames: list, prefix=(), block: bool = True) -> None:
        """Send one message; `prefix` is the ROUTER envelope (the peer's
        identity). Copied into zmq's own buffers: zero-copy sends of
        Python arrays that were still queued when a process ended, or when
        a saturated link held them for seconds, crashed it (libzmq's "Bad
        address (src/tcp.cpp:227)" abort, or a segfault: the server behind
        a 40 Mbit/s link, tests/test_netns_link.py); the copy costs about
        a millisecond a 4 MiB eye job message. Raises Unreachable for an
        unknown identity on a
        ROUTER, WouldBlock when not blocking and the queue is full."""
        try:
            self._raw.send_multipart([*prefix, *frames], copy=True, flags=0 if block else zmq.NOBLOCK)
        except zmq.ZMQError as e:
            raise _translated(e) from None

    def recv(self, accept=None, block: bool = True) -> tuple[list, Message]:
        """(envelope, message). A bad message raises WireError with
        `.prefix` set, so the caller can reply; nothing waiting when not
        blocking raises WouldBlock."""
        try:
            parts = self._raw.recv_multipart(copy=False, flags=0 if block else zmq.NOBLOCK)
        except zmq.ZMQError as e:
            raise _translated(e) from None
        # One identity frame on a ROUTER: DEALERs send no delimiter.
        prefix, frames = ([parts[0].bytes], parts[1:]) if self.is_router else ([], parts)
        size = sum(len(f) for f in frames)
        self.bytes_in += size
        try:
            msg = decode(frames, accept)
        except WireError as e:
            e.prefix = prefix
            raise
        self.bytes_in_by_type[msg.type] = self.bytes_in_by_type.get(msg.type, 0) + size
        return prefix, msg

    def recv_or_reply(self, accept=None, block: bool = True) -> tuple[list, Message] | None:
        """`recv`, except that a bad message is logged, answered (never an
        error with an error) and returns None."""
        try:
            return self.recv(accept, block)
        except WireError as e:
            who = e.prefix[0] if e.prefix else b"peer"
            log.warning("bad message from %r: %s", who, e)
            if e.msg_type not in ("error", "refused"):
                try:
                    self.send(error_reply(e), e.prefix, block=False)
                except TransportError as t:   # the sender is gone or flooded: the log line stands
                    log.warning("could not answer %r: %s", who, t)
            return None

    def drain(self, accept=None, limit: int | None = None):
        """Yield (envelope, message) for each message already waiting,
        without blocking; bad ones are answered and skipped (`recv_or_reply`)
        but count towards `limit`, which keeps a flood from starving the
        caller's other work."""
        taken = 0
        while limit is None or taken < limit:
            taken += 1
            try:
                got = self.recv_or_reply(accept, block=False)
            except WouldBlock:
                return
            if got is not None:
                yield got

    def poll(self, timeout_ms: int) -> bool:
        """True once a message waits, within `timeout_ms`."""
        try:
            return bool(self._raw.poll(timeout_ms))
        except zmq.ZMQError as e:
            raise _translated(e) from None

    def close(self, linger_ms: int = LINGER_MS) -> None:
        self._raw.close(linger=linger_ms)


class Poller:
    """Waits on several Sockets at once (for messages to receive)."""

    def __init__(self, *sockets: Socket):
        self._poller = zmq.Poller()
        self._sockets: dict[zmq.Socket, Socket] = {}
        for s in sockets:
            self.register(s)

    def register(self, socket: Socket) -> None:
        self._poller.register(socket._raw, zmq.POLLIN)
        self._sockets[socket._raw] = socket

    def unregister(self, socket: Socket) -> None:
        self._poller.unregister(socket._raw)
        del self._sockets[socket._raw]

    def poll(self, timeout_ms: int) -> set[Socket]:
        """The sockets with a message waiting, within `timeout_ms`."""
        try:
            return {self._sockets[raw] for raw, _ in self._poller.poll(timeout_ms)}
        except zmq.ZMQError as e:
            raise _translated(e) from None


def _configured(context: zmq.Context | None, kind: int) -> zmq.Socket:
    """A new socket with the back-pressure policy above (set before
    bind/connect, where zmq reads it)."""
    raw = (context or zmq.Context.instance()).socket(kind)
    raw.setsockopt(zmq.SNDHWM, HWM_MESSAGES)
    raw.setsockopt(zmq.RCVHWM, HWM_MESSAGES)
    raw.setsockopt(zmq.LINGER, LINGER_MS)
    raw.setsockopt(zmq.MAXMSGSIZE, MAX_FRAME_BYTES)
    raw.setsockopt(zmq.TCP_KEEPALIVE, 1)
    raw.setsockopt(zmq.TCP_KEEPALIVE_IDLE, TCP_KEEPALIVE_IDLE_S)
    raw.setsockopt(zmq.TCP_KEEPALIVE_INTVL, TCP_KEEPALIVE_INTVL_S)
    raw.setsockopt(zmq.TCP_KEEPALIVE_CNT, TCP_KEEPALIVE_CNT)
    if kind == zmq.ROUTER:
        raw.setsockopt(zmq.ROUTER_MANDATORY, 1)
        raw.setsockopt(zmq.ROUTER_HANDOVER, 1)
    return raw


def router(context: zmq.Context | None = None) -> Socket:
    """A ROUTER (the server's, or a tracer's for its peers); the shared
    process context unless one is given."""
    return Socket(_configured(context, zmq.ROUTER))


def dealer(identity: str | bytes, context: zmq.Context | None = None) -> Socket:
    """A DEALER that the ROUTER it connects to knows as `identity` (a
    tracer's id: a reconnect keeps it)."""
    raw = _configured(context, zmq.DEALER)
    raw.setsockopt(zmq.IDENTITY, identity.encode() if isinstance(identity, str) else identity)
    return Socket(raw)


# -- CURVE ----------------------------------------------------------------------
def finish_process() -> None:
    """Before the process exits: let the shared context's queued messages
    go (each socket's linger, LINGER_MS at most: a server's goodbyes, a
    tracer's last results) and stop its I/O thread. Without it the thread
    dies with the process and LINGER_MS means nothing. The linger is set
    again on every socket first: one made elsewhere (zmq's default linger
    is forever) would hold `term` until its peer took its last message,
    and a process whose peers are gone would never exit."""
    ctx = zmq.Context._instance
    if ctx is not None and not ctx.closed:
        ctx.destroy(linger=LINGER_MS)


def make_keys(directory: str, name: str) -> tuple[str, str]:
    """A CURVE key pair as ZeroMQ certificate files: NAME.key_secret (keep
    it on that host only, mode 0600) and NAME.key (public, to hand out)."""
    os.makedirs(directory, exist_ok=True)
    public, secret = zmq.auth.create_certificates(directory, name)
    os.chmod(secret, 0o600)
    return public, secret


def load_keys(path: str) -> tuple[bytes, bytes | None]:
    """(public, secret) from a certificate file; secret None for a public one."""
    try:
        return zmq.auth.load_certificate(path)
    except (OSError, ValueError) as e:
        raise CurveError(f"{path}: not a CURVE certificate: {e}") from None


def _key_pair(secret_file: str) -> tuple[bytes, bytes]:
    public, secret = load_keys(secret_file)
    if secret is None:
        raise CurveError(f"{secret_file}: holds no secret key")
    return public, secret


def curve_server(socket: Socket, secret_file: str) -> bytes:
    """Make `socket` a CURVE server with the key pair in `secret_file`
    (before bind); only clients the authenticator admits get through.
    Returns its public key."""
    public, secret = _key_pair(secret_file)
    raw = socket._raw
    try:
        raw.curve_secretkey, raw.curve_publickey, raw.curve_server = secret, public, True
    except zmq.ZMQError as e:
        raise CurveError(f"{secret_file}: {e}") from None
    return public


def curve_client(socket: Socket, secret_file: str, server_public: bytes) -> None:
    """Make `socket` a CURVE client of the server whose public key is given
    (before connect)."""
    public, secret = _key_pair(secret_file)
    raw = socket._raw
    try:
        raw.curve_secretkey, raw.curve_publickey, raw.curve_serverkey = secret, public, server_public
    except zmq.ZMQError as e:   # a server key of the wrong length or alphabet
        raise CurveError(f"CURVE key of the server or peer: {e}") from None


_HANDSHAKE_EVENTS = {zmq.EVENT_HANDSHAKE_SUCCEEDED: "accepted", zmq.EVENT_HANDSHAKE_FAILED_AUTH: "refused",
                     zmq.EVENT_HANDSHAKE_FAILED_PROTOCOL: "refused", zmq.EVENT_HANDSHAKE_FAILED_NO_DETAIL: "refused"}


def handshake(endpoint: str, secret_file: str | None = None, server_public: bytes | None = None,
              timeout_s: float = 3.0) -> str:
    """Probe a socket: how a connection to `endpoint` (as a CURVE client
    with the key pair in `secret_file`, or in plain text without one) ends
    its handshake: 'accepted', 'refused', or 'silent' (no answer within
    `timeout_s`). Nothing is sent."""
    raw = zmq.Context.instance().socket(zmq.DEALER)
    raw.setsockopt(zmq.LINGER, 0)
    if secret_file:
        public, secret = _key_pair(secret_file)
        raw.curve_secretkey, raw.curve_publickey, raw.curve_serverkey = secret, public, server_public
    events = 0
    for e in _HANDSHAKE_EVENTS:
        events |= e
    monitor = raw.get_monitor_socket(events)
    try:
        raw.connect(endpoint)
        if monitor.poll(int(timeout_s * 1000)):
            return _HANDSHAKE_EVENTS[zmq.utils.monitor.recv_monitor_message(monitor)["event"]]
        return "silent"
    finally:
        raw.disable_monitor()
        monitor.close()
        raw.close()


def start_authenticator(clients_dir: str, context: zmq.Context | None = None) -> ThreadAuthenticator:
    """Admit only CURVE clients whose public key files are in `clients_dir`
    (ZeroMQ's ZAP handler on a thread, for every socket of the context);
    returns it, to `stop()`."""
    if not os.path.isdir(clients_dir):
        raise CurveError(f"{clients_dir}: no such directory of public keys")
    auth = ThreadAuthenticator(context or zmq.Context.instance())
    auth.start()
    auth.configure_curve(domain="*", location=clients_dir)
    return auth
