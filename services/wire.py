"""The wire protocol of the distributed service (DOSPPM, Günther & Grosch
§3.1 "Network", §3.3, §4.3): every message, the protocol version, encoding
and validation. A codec only: `services.transport` moves the frames over
ZeroMQ sockets (and is the only module that imports zmq). How a message
is declared and the frame codec every message shares are in
services/_wire_codec.py, which only this module imports: the rest import
the protocol from here.

API
---
    encode(msg_type, **fields) -> [header bytes, memoryview, ...]
    decode(frames, accept=None) -> Message(type, fields, version); msg.job, msg.batch
    WireError(ValueError), VersionMismatch(WireError): .msg_type, .field, .prefix
    error_reply(e) -> frames of `error`, or `refused` for a register in another version
    chunk_parts(chunk, sha256, data) -> [frames of each chunk_data part]
    Out(dest, type, fields): a message to send, as the roles' state machines return it
    MESSAGES (name -> Spec), JOB_MESSAGES, describe() -> the message table

Framing
-------
A message is one ZeroMQ multipart message:

    frame 0      msgpack map {"v": PROTOCOL_VERSION, "type": str, <fields>,
                              "arrays": [{"name", "dtype", "shape"}, ...]}
    frame 1..k   the raw bytes of each array listed in "arrays", in order

Dtypes are numpy strings, always little-endian ("<f4", "<i4", "<u8", "|u1");
shapes are lists of ints. Arrays travel out of band: `encode` returns
memoryviews of the caller's arrays (sent with `copy=False`), and `decode`
wraps each frame with `np.frombuffer` (both through the one array codec,
`dosppm_core.arrays`), so a 1M-ray batch is never copied by this module.
Exception: a frame that libzmq hands over misaligned for its dtype (small
frames over tcp sit at odd offsets in the receive buffer) is copied,
because numba's kernels want aligned arrays. Decoded arrays may be
read-only (a `bytes` frame); copy before writing in place. No pickle.

Records (`RayBatch`, `PhotonDeposits`, `HitPoints`, `ShadowRays`) travel as one array per
field, named "<field>.<column>" (e.g. "batch.origin"), with dtypes and
trailing shapes taken from the record class's SCHEMA, so the wire follows
the library. A decoded message rebuilds them: `msg.batch` is a `RayBatch`.
A record's optional column (`_Record.OPTIONAL`: the hit points' `frame`)
travels only when the record has it; decoded without it, it is None.

Validation
----------
`decode` checks everything before returning, and raises `WireError` (a
ValueError) with one line naming the message type and field: header not
msgpack or not a map, unknown type, missing or foreign version (naming
both), missing or unexpected field, wrong scalar type, array count vs frame
count, unknown/missing/duplicate array, dtype, shape or trailing dims, size
over MAX_ELEMENTS or unlike its frame's, unequal record lengths, non-finite
floats (only the cull box may hold +-inf, "no culling"), and per-message
rules (the specs' `check`s): ints >= 0 fitting int64; results' ends >= 0,
none CONTINUES, an eye_iteration with hits or light; a photon portal_rays
with a cull box and no eye_iteration, an eye one the reverse; a photon_job
or eye_job's distinct ids, counts >= 1 summing to at most MAX_EMITTED, one
credit term per job. Nothing else escapes
`decode`: callers answer a WireError with `error_reply` and a log line
(`transport.Socket.recv_or_reply` does both) and carry on. Ranges the wire
cannot know (pixels, tiles, chunks, materials) are checked by the role that
knows them. Only `error` and `refused` decode whatever the (int) version:
their fields are frozen, so a peer speaking another version can still read
why it was turned away.

Messages
--------
    tracer -> server
      register       tracer_id, capacity {cores, memory_bytes}, endpoint
                     (its peer ROUTER), has_store, store_key|None,
                     public_key|None (its CURVE key, for its peers)
      heartbeat      status {} (informational: queue, load, resident chunks)
      results        chunk (None: an emission), culled, queued, queue_target
                     (rays it asks to have queued; 0: the server's default),
                     eye_iteration|None, ends i64 (5,),
                     job_ids + job_fed + job_left i64 (k,), credit
                     returned (credit_job + credit_exp i64); optional
                     deposits: PhotonDeposits, hits: HitPoints,
                     emitted_pixels i32 (m,) + emitted_rgb f32 (m, 3) (light
                     seen, unless held: light_request); hit_points_made
      chunk_request  chunk
      error          reason, about|None                 (any direction)
    server -> tracer
      welcome        tracer_index, settings {}, scene {} (SceneHeader.to_wire),
                     tree {} (ChunkTree.to_wire), store_key, chunks [int],
                     manifest {}|None (for tracers without the store)
      refused        reason
      peers          table_version, peers [[endpoint]] indexed by chunk,
                     keys {endpoint: CURVE public key} (with CURVE)
      photon_job     job_ids + rng_keys + counts i64 (n,): jobs whose photons
                     the tracer makes (seed, rng key, count); cull_box f64
                     (2, 3), credit (credit_job + credit_exp i64: one term
                     per job)
      eye_job        eye_iteration; job_ids + pixel_starts + counts i64 (n,):
                     tiles whose eye rays the tracer makes (seed, eye
                     iteration, pixels [start, start + count)), credit
                     (one term per job)
      chunk_data     chunk, sha256, part, parts, offset, file_bytes, data u8
      heartbeat, shutdown (reason)
      hit_points     hits_version (the eye iteration), hits: HitPoints, in the
                     order the server's statistics hold them (gather at tracers)
      gather         epoch, epochs (merged: epoch .. epoch + epochs - 1), phase
                     "count"|"pilot"|"sums", hits_version, total +
                     most (the pilot's subsample), job_ids + job_boxes f64 (k, 2, 3)
                     (the epoch's jobs, own cull boxes), rows i64 + radius f64
                     (m,) (hit point rows: fresh ones for a pilot, all for sums)
      drop_epoch     epoch: discarded, its held deposits are dropped
      light_request  round, eye_iterations i64 (k,): whose held light to send
    tracer -> server (gather at tracers)
      epoch_sums     epoch, phase, hits_version, deposits (held in the jobs' own
                     boxes), chosen (pilot subsample), flux f64 (3,), m f64
                     (k,) + phi f64 (k, 3) per hit point row, rows i64 (k,)
                     when sparse (absent: every row, in order)
      eye_light      round, pixels i32 (m,) + rgb f32 (m, 3): their light, summed
    tracer -> tracer
      portal_rays    kind "photon"|"eye"|"shadow", chunk (the destination),
                     eye_iteration (eye, shadow), cull_box (photon only),
                     batch: RayBatch (photon, eye) or shadows: ShadowRays,
                     credit

`MESSAGES` holds the specs; `describe()` prints this table from them.

Exact accounting (job ids, path counts, credit): docs/how-it-works.md.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from dosppm_core.jobs import CONTINUES, END_NAMES, HitPoints, PhotonDeposits, RayBatch, ShadowRays
from services import credit
# The declaration vocabulary and the generic frame codec (no message of
# their own) are kept apart so that this module reads as the protocol:
# the version, the limits, every message and its rules, the calls.
from services._wire_codec import (
    BOOL, DATA, FINITE, INT, MAX_ELEMENTS, NOT_NAN, STR, Choice, Group, Hex, Int, ListOf, Nullable, Spec,
    Struct, WireError, pack, plain, read_fields, read_header, record, shape_text,
)

PROTOCOL_VERSION = 10  # 2 shadow rays; 3 credit; 4 photon jobs made by the tracer; 5 the gather at the
                       # tracers; 6 eye tiles made by the tracer; 7 eye light held at the tracers;
                       # 8 deposits without a normal; 9 hit points' optional frame; 10 merged epochs

# -- policy ---------------------------------------------------------------------
# MAX_ELEMENTS (the codec's cap on one array's declared size) bounds a frame:
MAX_FRAME_BYTES = MAX_ELEMENTS * 8   # the largest frame a socket takes (transport's MAXMSGSIZE)
CHUNK_PART_BYTES = 16 << 20      # chunk_data splits chunk files into parts this big
# Paths one job message may ask a tracer to make (64 B each: 4M is 256 MB):
# bounds what a few bytes can make a tracer allocate, as MAX_ELEMENTS does.
MAX_EMITTED = 1 << 22
# The rounds of an epoch's gather at the tracers (services/tracer/epochs.py).
GATHER_PHASES = ("count", "pilot", "sums")


class VersionMismatch(WireError):
    """The peer speaks another protocol version (`theirs`, `ours`)."""

    def __init__(self, msg_type: str, theirs):
        super().__init__(f"{msg_type}: protocol version {theirs!r} from peer, this process speaks "
                         f"version {PROTOCOL_VERSION}", msg_type, "v")
        self.theirs, self.ours = theirs, PROTOCOL_VERSION


# -- message specs --------------------------------------------------------------
def _cull_box(optional: bool = False) -> Group:
    # +-inf allowed: NO_CULL is [-inf, inf]; NaN would make culling undefined.
    return plain("cull_box", ("cull_box", np.float64, (3,), NOT_NAN), rows=2, optional=optional)


def _credit() -> Group:
    return plain("credit", ("credit_job", np.int64, (), None), ("credit_exp", np.int64, (), None))


def _check_credit(f: dict) -> str | None:
    """Exponents bounded, so a hostile message cannot make the server's
    exact sums huge (services/credit.py)."""
    e = f["credit_exp"]
    if len(e) and (e.min() < 0 or e.max() > credit.MAX_EXP):
        return f"field 'credit_exp' needs 0 <= exponent <= {credit.MAX_EXP}"
    if (f["credit_job"] < 0).any():
        return "field 'credit_job' has a negative job id"
    return None


def _check_jobs(f: dict, keys_field: str, what: str) -> str | None:
    """A job message's jobs (photon_job, eye_job): each made by the tracer
    from its key and count, so the counts bound what it allocates."""
    problem = _check_credit(f)
    if problem:
        return problem
    ids, keys, counts = f["job_ids"], f[keys_field], f["counts"]
    if (ids < 0).any() or (keys < 0).any():
        return f"fields 'job_ids'/'{keys_field}' need {what} >= 0"
    if (counts < 1).any() or (counts > MAX_EMITTED).any() or int(counts.sum()) > MAX_EMITTED:
        return f"field 'counts' needs counts >= 1 summing to at most {MAX_EMITTED}"
    if len(np.unique(ids)) != len(ids):
        return "field 'job_ids' lists a job twice"
    if not np.array_equal(np.sort(f["credit_job"]), np.sort(ids)):
        return "field 'credit_job' needs one term per job of 'job_ids'"
    return None


def _check_results(f: dict) -> str | None:
    problem = _check_credit(f)
    if problem:
        return problem
    ends = f["ends"]
    if (ends < 0).any():
        return f"field 'ends' has a negative count {ends.tolist()}"
    if ends[CONTINUES] != 0:
        return (f"field 'ends' counts {int(ends[CONTINUES])} continuing paths; a path that goes on "
                f"is not an end")
    fed, left = f["job_fed"], f["job_left"]
    if (fed <= 0).any() or (left < 0).any() or (left > fed).any():
        return "fields 'job_fed'/'job_left' need 0 <= left <= fed and fed > 0"
    if int((fed - left).sum()) != int(ends.sum()):
        return (f"fields 'job_fed' - 'job_left' sum to {int((fed - left).sum())}, but 'ends' counts "
                f"{int(ends.sum())} ended paths")
    if (f.get("hits") is not None or f.get("emitted_pixels") is not None) and f["eye_iteration"] is None:
        return "field 'eye_iteration' is required with hits or emitted light"
    return "field 'hit_points_made' is negative" if f["hit_points_made"] < 0 else None


def _check_portal_rays(f: dict) -> str | None:
    problem = _check_credit(f)
    if problem:
        return problem
    photon, shadow = f["kind"] == "photon", f["kind"] == "shadow"
    if photon and (f.get("cull_box") is None or f["eye_iteration"] is not None):
        return "field 'cull_box' is required and 'eye_iteration' must be None for photons"
    if not photon and (f.get("cull_box") is not None or f["eye_iteration"] is None):
        return "field 'eye_iteration' is required and 'cull_box' must be absent for eye and shadow rays"
    if (f.get("shadows") is not None) != shadow or (f.get("batch") is not None) == shadow:
        return "kind 'shadow' carries 'shadows' (ShadowRays), kinds 'photon' and 'eye' a 'batch'"
    return None


def _check_chunk_data(f: dict) -> str | None:
    if f["part"] >= f["parts"]:
        return f"field 'part' {f['part']} is not below parts {f['parts']}"
    if f["offset"] + len(f["data"]) > f["file_bytes"]:
        return f"field 'data' ends at {f['offset'] + len(f['data'])}, past file_bytes {f['file_bytes']}"
    return None


def _increasing(a: np.ndarray) -> bool:
    return not len(a) or (a[0] >= 0 and bool((a[1:] > a[:-1]).all()))


def _check_gather(f: dict) -> str | None:
    if not _increasing(f["job_ids"]):
        return "field 'job_ids' needs ids >= 0 in increasing order"
    if not _increasing(f["rows"]):
        return "field 'rows' needs hit point rows >= 0 in increasing order"
    if (f["radius"] <= 0).any():
        return "field 'radius' needs radii > 0"
    if f["phase"] == "pilot" and (f["total"] < 1 or f["most"] < 1):
        return "fields 'total'/'most' need to be >= 1 for phase 'pilot'"
    return None


def _check_epoch_sums(f: dict) -> str | None:
    rows = f.get("rows")
    if rows is not None and (len(rows) != len(f["m"]) or not _increasing(rows)):
        return "field 'rows' needs one increasing row >= 0 per sum"
    if (f["m"] < 0).any():
        return "field 'm' needs counts >= 0"
    if f["phase"] != "sums" and len(f["phi"]) and f["phi"].any():
        return "field 'phi' must be zero outside phase 'sums'"
    return None


def _increasing_field(name: str):
    """The check that array field `name` holds distinct values >= 0, increasing."""
    return lambda f: None if _increasing(f[name]) else f"field {name!r} needs values >= 0 in increasing order"


_T2S, _S2T, _T2T, _ANY = "tracer->server", "server->tracer", "tracer->tracer", "any->any"
_SPECS = (
    Spec("register", _T2S, {"tracer_id": STR, "capacity": Struct(cores=Int(1), memory_bytes=INT),
                            "endpoint": STR, "has_store": BOOL, "store_key": Nullable(STR),
                            "public_key": Nullable(STR)},
         defaults={"store_key": None, "public_key": None}),
    Spec("heartbeat", "both", {"status": DATA}, defaults={"status": {}}),
    Spec("results", _T2S, {"chunk": Nullable(INT), "culled": INT, "queued": INT, "queue_target": INT,
                           "eye_iteration": Nullable(INT), "hit_points_made": INT},
         (plain("ends", ("ends", np.int64, (), None), rows=len(END_NAMES)),
          plain("job_paths", ("job_ids", np.int64, (), None), ("job_fed", np.int64, (), None),
                ("job_left", np.int64, (), None)),
          _credit(),
          record("deposits", PhotonDeposits, optional=True),
          record("hits", HitPoints, optional=True),
          plain("emitted", ("emitted_pixels", np.int32, (), None),
                 ("emitted_rgb", np.float32, (3,), FINITE), optional=True)),
         check=_check_results, defaults={"culled": 0, "queued": 0, "queue_target": 0, "eye_iteration": None,
                                         "hit_points_made": 0}),
    Spec("chunk_request", _T2S, {"chunk": INT}),
    Spec("error", _ANY, {"reason": STR, "about": Nullable(STR)}, any_version=True,
         defaults={"about": None}),
    Spec("welcome", _S2T, {"tracer_index": INT, "settings": DATA, "scene": DATA, "tree": DATA,
                           "store_key": STR, "chunks": ListOf(INT), "manifest": Nullable(DATA)},
         defaults={"manifest": None}),
    Spec("refused", _S2T, {"reason": STR}, any_version=True),
    Spec("peers", _S2T, {"table_version": INT, "peers": ListOf(ListOf(STR)), "keys": DATA},
         defaults={"keys": {}}),
    Spec("photon_job", _S2T, {},
         (plain("jobs", ("job_ids", np.int64, (), None), ("rng_keys", np.int64, (), None),
                ("counts", np.int64, (), None)), _cull_box(), _credit()),
         check=lambda f: _check_jobs(f, "rng_keys", "ids and keys")),
    Spec("eye_job", _S2T, {"eye_iteration": INT},
         (plain("tiles", ("job_ids", np.int64, (), None), ("pixel_starts", np.int64, (), None),
                ("counts", np.int64, (), None)), _credit()),
         check=lambda f: _check_jobs(f, "pixel_starts", "ids and pixel starts")),
    Spec("chunk_data", _S2T, {"chunk": INT, "sha256": Hex(), "part": INT, "parts": Int(1),
                              "offset": INT, "file_bytes": INT},
         (plain("data", ("data", np.uint8, (), None)),), check=_check_chunk_data),
    Spec("shutdown", _S2T, {"reason": STR}, defaults={"reason": ""}),
    Spec("hit_points", _S2T, {"hits_version": INT}, (record("hits", HitPoints),)),
    Spec("gather", _S2T, {"epoch": INT, "epochs": Int(1), "phase": Choice(*GATHER_PHASES),
                          "hits_version": INT, "total": INT, "most": INT},
         (plain("jobs", ("job_ids", np.int64, (), None), ("job_boxes", np.float64, (2, 3), NOT_NAN)),
          plain("radii", ("rows", np.int64, (), None), ("radius", np.float64, (), FINITE))),
         check=_check_gather, defaults={"epochs": 1, "total": 0, "most": 0}),
    Spec("drop_epoch", _S2T, {"epoch": INT}),
    Spec("light_request", _S2T, {"round": INT}, (plain("iterations", ("eye_iterations", np.int64, (), None)),),
         check=_increasing_field("eye_iterations")),
    Spec("eye_light", _T2S, {"round": INT}, (plain("light", ("pixels", np.int32, (), None),
                                                     ("rgb", np.float32, (3,), FINITE)),),
         check=_increasing_field("pixels")),
    Spec("epoch_sums", _T2S, {"epoch": INT, "phase": Choice(*GATHER_PHASES), "hits_version": INT,
                              "deposits": INT, "chosen": INT},
         (plain("flux", ("flux", np.float64, (), FINITE), rows=3),
          plain("sums", ("m", np.float64, (), FINITE), ("phi", np.float64, (3,), FINITE)),
          plain("sparse", ("rows", np.int64, (), None), optional=True)),
         check=_check_epoch_sums, defaults={"deposits": 0, "chosen": 0}),
    Spec("portal_rays", _T2T, {"kind": Choice("photon", "eye", "shadow"), "chunk": INT,
                               "eye_iteration": Nullable(INT)},
         (_cull_box(optional=True), record("batch", RayBatch, optional=True),
          record("shadows", ShadowRays, optional=True), _credit()),
         check=_check_portal_rays, defaults={"eye_iteration": None}),
)
MESSAGES: dict[str, Spec] = {s.name: s for s in _SPECS}
# The messages that carry work to a tracer: counted by both ends since the
# tracer's welcome, and acknowledged in its heartbeats.
JOB_MESSAGES = ("photon_job", "eye_job")


def describe() -> str:
    """The message table, from the specs (for docs and `--help`)."""
    lines = []
    for s in _SPECS:
        cols = [f"{k}: {t.label}" for k, t in s.fields.items()]
        for g in s.groups:
            what = (g.record.__name__ if g.record else
                    ", ".join(f"{c.key + ' ' if len(g.columns) > 1 else ''}{c.dtype.str} "
                              f"{shape_text(g.rows, c.trailing)}" for c in g.columns))
            cols.append(f"{g.name}{'?' if g.optional else ''}: {what}")
        lines.append(f"{s.name:14s} {s.route:15s} " + "; ".join(cols))
    return "\n".join(lines)


# -- the message ----------------------------------------------------------------
@dataclass
class Message:
    """A decoded message: `fields` holds scalars, plain arrays and records
    (absent optional groups are None); `msg.job` reads `msg.fields["job"]`."""
    type: str
    fields: dict
    version: int = PROTOCOL_VERSION

    def __getattr__(self, name):
        fields_ = self.__dict__.get("fields")
        if fields_ is not None and name in fields_:
            return fields_[name]
        raise AttributeError(f"{self.__dict__.get('type', 'message')!s} has no field {name!r}")


@dataclass
class Out:
    """A message to send, as the server's and the tracer's state machines
    return it: `dest` is a tracer id, a peer endpoint or the server; the
    I/O shell encodes `type` and `fields` with `encode`."""
    dest: str
    type: str
    fields: dict


# -- encode and decode ----------------------------------------------------------
def encode(msg_type: str, **fields_) -> list:
    """Frames for one message: [header bytes, array memoryviews...]. The
    result is checked by the same rules as `decode` (except the cheap-to-
    skip finiteness scan), so a sender's bug fails at the sender."""
    spec = MESSAGES.get(msg_type)
    if spec is None:
        raise WireError(f"unknown message type {msg_type!r}", msg_type, "type")
    frames = pack(spec, {"v": PROTOCOL_VERSION, "type": msg_type}, dict(fields_))
    _validate(frames, check_values=False)
    return frames


def _spec_and_version(header: dict) -> Spec:
    t = header.get("type")
    spec = MESSAGES.get(t) if type(t) is str else None
    if spec is None:
        raise WireError(f"unknown message type {t!r}"[:200], None, "type")
    v = header.get("v")
    if type(v) is not int:
        raise VersionMismatch(t, v)
    if v != PROTOCOL_VERSION and not spec.any_version:
        raise VersionMismatch(t, v)
    return spec


def _validate(frames, check_values: bool = True) -> Message:
    if len(frames) == 0:
        raise WireError("empty message: no header frame")
    header = read_header(frames[0])
    spec = _spec_and_version(header)
    out = read_fields(spec, header, frames, check_values)
    problem = spec.check(out) if spec.check else None
    if problem:
        raise WireError(f"{spec.name}: {problem}", spec.name)
    return Message(spec.name, out, header["v"])


def decode(frames, accept=None) -> Message:
    """The message in `frames` (bytes, memoryviews or zmq.Frames; the
    envelope already removed), checked; arrays are views of the frames.
    `accept`: the message types this role takes; others are refused.
    Raises only WireError."""
    try:
        msg = _validate(frames)
    except WireError:
        raise
    except Exception as e:   # a rule this module forgot must still not crash a process
        raise WireError(f"undecodable message: {type(e).__name__}: {e}"[:200]) from None
    if accept is not None and msg.type not in accept:
        raise WireError(f"{msg.type}: not accepted here (takes {', '.join(sorted(accept))})", msg.type)
    return msg


# -- replies --------------------------------------------------------------------
def refusal_reason(e: VersionMismatch) -> str:
    return (f"protocol version mismatch: tracer speaks {e.theirs!r}, server speaks {e.ours}; "
            f"run the same dosppm release on both")


def error_reply(e: WireError) -> list:
    """The answer to a bad message: `refused` for a register in another
    protocol version (it cannot join), `error` otherwise."""
    if isinstance(e, VersionMismatch) and e.msg_type == "register":
        return encode("refused", reason=refusal_reason(e))
    return encode("error", reason=str(e), about=e.msg_type)


def chunk_parts(chunk: int, sha256: str, data) -> list[list]:
    """A chunk file as `chunk_data` messages of at most CHUNK_PART_BYTES,
    each a view of `data` (no copy)."""
    buf = np.frombuffer(memoryview(data).cast("B"), np.uint8)
    size = len(buf)
    parts = max(1, -(-size // CHUNK_PART_BYTES))
    return [encode("chunk_data", chunk=chunk, sha256=sha256, part=p, parts=parts,
                   offset=p * CHUNK_PART_BYTES, file_bytes=size,
                   data=buf[p * CHUNK_PART_BYTES:(p + 1) * CHUNK_PART_BYTES])
            for p in range(parts)]
