"""The wire protocol (services/wire.py, issue 4 "The wire"): every message
round-trips bit-exactly without copying its arrays, every malformed message
is refused with a WireError naming type and field, and random damage never
raises anything else. Over real sockets: tests/test_transport.py."""
from __future__ import annotations

import dataclasses
import hashlib

import msgpack
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from dosppm_core.chunks.tree import ChunkTree
from dosppm_core.jobs import HitPoints, PhotonDeposits, RayBatch, ShadowRays
from dosppm_core.scene import builtin
from dosppm_core.scene.model import SceneHeader
from services import wire
from services.wire import PROTOCOL_VERSION, VersionMismatch, WireError, decode, encode
from tests.helpers.chunks import uniform_tree

FAST = settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.too_slow])


# -- random messages ------------------------------------------------------------
def random_record(cls, n: int, rng: np.random.Generator):
    """Every column filled with random bits of its dtype (finite floats)."""
    cols = {}
    for name, (dtype, trailing) in cls.SCHEMA.items():
        shape, dt = (n,) + tuple(trailing), np.dtype(dtype)
        if dt.kind == "f":
            cols[name] = rng.normal(0, 1e3, shape).astype(dt)
        else:
            info = np.iinfo(dt)
            cols[name] = rng.integers(info.min, info.max, shape, dtype=dt, endpoint=True)
    return cls(**cols)


NO_CREDIT = dict(credit_job=np.zeros(0, np.int64), credit_exp=np.zeros(0, np.int64))


def sample_fields(msg_type: str, n: int, rng: np.random.Generator, variant: int = 0) -> dict:
    """Valid fields for `msg_type` with records of `n` rows; `variant`
    picks which optional parts a results message carries (and the kind
    of a portal package: 0, 2 photon, 1 eye, 3 shadow)."""
    fields = _sample_fields(msg_type, n, rng, variant)
    if msg_type in ("results", "portal_rays"):
        fields.update(credit_job=rng.integers(0, 1000, n % 4, dtype=np.int64),
                      credit_exp=rng.integers(0, 300, n % 4, dtype=np.int64))
    return fields


def _sample_fields(msg_type: str, n: int, rng: np.random.Generator, variant: int) -> dict:
    box = np.array([[-1.0, -2.0, -3.0], [4.0, 5.0, np.inf]])
    batch = random_record(RayBatch, n, rng)
    if msg_type == "register":
        return dict(tracer_id="t-1", capacity={"cores": 8, "memory_bytes": 1 << 34},
                    endpoint="tcp://10.0.0.2:5701", has_store=bool(variant % 2),
                    store_key=None if variant % 2 else "abc123")
    if msg_type == "heartbeat":
        return dict(status={"queued_rays": n, "resident": [1, 2], "load": 0.5})
    if msg_type == "results":
        ends = rng.integers(0, 1000, 5).astype(np.int64) * np.array([0, 1, 1, 1, 1])
        f = dict(chunk=2, culled=n, queued=3 * n, eye_iteration=None, ends=ends,
                 job_ids=np.array([7, 9], np.int64), job_fed=np.array([1, ends.sum() + 2], np.int64),
                 job_left=np.array([0, 3], np.int64))
        if ends.sum() < 2:
            f.update(job_ids=np.array([7], np.int64)[:int(ends.sum())],
                     job_fed=np.array([1], np.int64)[:int(ends.sum())],
                     job_left=np.array([0], np.int64)[:int(ends.sum())])
        if variant in (0, 2):
            f["deposits"] = random_record(PhotonDeposits, n, rng)
        if variant in (1, 2):
            f.update(eye_iteration=3, hits=random_record(HitPoints, n, rng), hit_points_made=n + variant,
                     emitted_pixels=rng.integers(0, 1 << 20, n, dtype=np.int32),
                     emitted_rgb=rng.random((n, 3), dtype=np.float32))
        return f
    if msg_type == "chunk_request":
        return dict(chunk=n)
    if msg_type == "error":
        return dict(reason="results: field 'ends' is bad", about="results")
    if msg_type == "welcome":
        return dict(tracer_index=1, settings={"max_depth": 10, "alpha": 0.7}, scene={"name": "s"},
                    tree={"nodes": 1, "chunks": 1, "axis": b"\xff"}, store_key="k", chunks=[0, 3],
                    manifest=None)
    if msg_type == "refused":
        return dict(reason="full")
    if msg_type == "peers":
        return dict(table_version=4, peers=[["tcp://a:1"], [], ["tcp://b:2", "tcp://c:3"]])
    if msg_type == "photon_job":       # one credit term per job, as the wire wants
        ids = rng.choice(1 << 40, n, replace=False).astype(np.int64)
        return dict(job_ids=ids, rng_keys=rng.integers(0, 1 << 62, n, dtype=np.int64),
                    counts=rng.integers(1, 1 << 14, n, dtype=np.int64), cull_box=box,
                    credit_job=rng.permutation(ids), credit_exp=rng.integers(0, 300, n, dtype=np.int64))
    if msg_type == "eye_job":          # tiles: one credit term per job
        ids = rng.choice(1 << 40, n, replace=False).astype(np.int64)
        return dict(eye_iteration=5, job_ids=ids, pixel_starts=rng.integers(0, 1 << 20, n, dtype=np.int64),
                    counts=rng.integers(1, 1 << 14, n, dtype=np.int64), credit_job=rng.permutation(ids),
                    credit_exp=rng.integers(0, 300, n, dtype=np.int64))
    if msg_type == "chunk_data":
        data = rng.integers(0, 256, n, dtype=np.uint8)
        return dict(chunk=3, sha256=hashlib.sha256(data).hexdigest(), part=0, parts=1, offset=0,
                    file_bytes=n, data=data)
    if msg_type == "shutdown":
        return dict(reason="time limit")
    if msg_type in ("hit_points", "gather", "drop_epoch", "epoch_sums"):
        return _epoch_fields(msg_type, n, rng, variant, box)
    if msg_type == "light_request":
        return dict(round=variant, eye_iterations=np.sort(rng.choice(1 << 30, n, replace=False)).astype(np.int64))
    if msg_type == "eye_light":
        return dict(round=variant, pixels=np.sort(rng.choice(1 << 20, n, replace=False)).astype(np.int32),
                    rgb=rng.random((n, 3), dtype=np.float32))
    if msg_type == "portal_rays":
        if variant == 3:
            return dict(kind="shadow", chunk=4, eye_iteration=2, shadows=random_record(ShadowRays, n, rng))
        if variant % 2:
            return dict(kind="eye", chunk=4, eye_iteration=2, batch=batch)
        return dict(kind="photon", chunk=4, cull_box=box, batch=batch)
    raise AssertionError(msg_type)


def _epoch_fields(msg_type: str, n: int, rng: np.random.Generator, variant: int, box) -> dict:
    """The gather at the tracers' messages (variant: which phase, dense or sparse sums)."""
    if msg_type == "hit_points":
        return dict(hits_version=2, hits=random_record(HitPoints, n, rng))
    if msg_type == "drop_epoch":
        return dict(epoch=4)
    phase = wire.GATHER_PHASES[variant % 3]
    if msg_type == "gather":
        return dict(epoch=3, phase=phase, hits_version=1, total=n + 1, most=n + 1,
                    job_ids=np.arange(n, dtype=np.int64) * 3, job_boxes=np.tile(box, (n, 1, 1)),
                    rows=np.arange(n, dtype=np.int64), radius=rng.uniform(0.1, 1, n))
    f = dict(epoch=3, phase=phase, hits_version=1, deposits=n, chosen=0, flux=rng.random(3),
             m=rng.integers(0, 5, n).astype(np.float64),
             phi=rng.random((n, 3)) if phase == "sums" else np.zeros((n, 3)))
    if variant == 3:
        f["rows"] = np.arange(n, dtype=np.int64) * 2
    return f


def as_bytes(frames) -> list[bytes]:
    """What a receiver holds: fresh buffers, not the sender's arrays."""
    return [bytes(f) for f in frames]


def arrays_of(fields: dict) -> dict:
    """{name: array} of every array a message's fields hold, records flattened."""
    out = {}
    for k, v in fields.items():
        if isinstance(v, np.ndarray):
            out[k] = v
        elif hasattr(v, "SCHEMA"):
            out.update({f"{k}.{c}": a for c, a in v.arrays().items()})
    return out


def assert_same_message(sent: dict, msg) -> None:
    got = arrays_of(msg.fields)
    want = arrays_of(sent)
    assert set(got) == set(want)
    for k, a in want.items():
        assert got[k].dtype == a.dtype and got[k].shape == a.shape, k
        assert got[k].tobytes() == a.tobytes(), k   # bit-equal, NaN-safe
    for k, v in sent.items():
        if k not in msg.fields or isinstance(v, np.ndarray) or hasattr(v, "SCHEMA"):
            continue
        assert msg.fields[k] == v, k


def frame_views(frames) -> list[np.ndarray]:
    return [np.frombuffer(f, np.uint8) for f in frames[1:]]


# -- round trips ------------------------------------------------------------------
@FAST
@given(msg_type=st.sampled_from(sorted(wire.MESSAGES)), n=st.integers(0, 40),
       seed=st.integers(0, 2**32 - 1), variant=st.integers(0, 3))
def test_every_message_round_trips_bit_exact_without_copying(msg_type, n, seed, variant):
    sent = sample_fields(msg_type, n, np.random.default_rng(seed), variant)
    frames = as_bytes(encode(msg_type, **sent))
    msg = decode(frames)
    assert msg.type == msg_type and msg.version == PROTOCOL_VERSION
    assert_same_message(sent, msg)
    # Zero-copy decode: each non-empty array is a view of its frame.
    bufs = frame_views(frames)
    for name, a in arrays_of(msg.fields).items():
        if a.size:
            assert any(np.shares_memory(a, b) for b in bufs), name
    # Decoded messages re-encode to the same bytes (a tracer may forward one).
    assert as_bytes(encode(msg.type, **msg.fields)) == frames


def test_records_come_back_as_library_classes():
    rng = np.random.default_rng(1)
    msg = decode(encode("results", **sample_fields("results", 5, rng, variant=2)))
    assert isinstance(msg.deposits, PhotonDeposits) and isinstance(msg.hits, HitPoints)
    assert msg.emitted_rgb.shape == (5, 3) and msg.ends.dtype == np.int64
    msg = decode(encode("portal_rays", **sample_fields("portal_rays", 5, rng)))
    assert isinstance(msg.batch, RayBatch) and len(msg.batch) == 5
    assert msg.cull_box.dtype == np.float64 and msg.cull_box[1, 2] == np.inf
    empty = decode(encode("results", chunk=0, ends=np.zeros(5, np.int64),
                          job_ids=np.zeros(0, np.int64), job_fed=np.zeros(0, np.int64),
                          job_left=np.zeros(0, np.int64), credit_job=np.zeros(0, np.int64),
                          credit_exp=np.zeros(0, np.int64)))
    assert empty.deposits is None and empty.hits is None and empty.emitted_pixels is None


def test_a_hit_points_frame_travels_only_when_it_has_one():
    """`HitPoints.frame` is optional (scenes without an anisotropic
    material carry none): without it the message lists no such array and
    decodes to None; with it, it comes back bit-equal (the round trip
    above); a frame of the wrong width is refused naming it."""
    rng = np.random.default_rng(4)
    fields = sample_fields("results", 6, rng, variant=1)
    fields["hits"] = dataclasses.replace(fields["hits"], frame=None)
    frames = encode("results", **fields)
    names = [e["name"] for e in msgpack.unpackb(frames[0])["arrays"]]
    assert "hits.position" in names and "hits.frame" not in names
    msg = decode(as_bytes(frames))
    assert msg.hits.frame is None and len(msg.hits) == 6
    fields = sample_fields("results", 6, rng, variant=1)
    fields["hits"] = dataclasses.replace(fields["hits"], frame=np.zeros((6, 4), np.float32))
    with pytest.raises(WireError, match="results.*'hits.frame'"):
        encode("results", **fields)


def test_encode_is_zero_copy_on_the_senders_arrays():
    batch = random_record(RayBatch, 1000, np.random.default_rng(2))
    frames = encode("portal_rays", kind="eye", eye_iteration=0, chunk=0, batch=batch,
                    credit_job=np.zeros(1, np.int64), credit_exp=np.zeros(1, np.int64))
    for col, view in zip(RayBatch.SCHEMA, frame_views(frames)):
        assert np.shares_memory(view, getattr(batch, col)), col


def test_welcome_carries_a_real_scene_header_and_chunk_tree():
    header = builtin.cornell_box().header()
    tree = uniform_tree(header.bounds, (2, 1, 2))
    msg = decode(as_bytes(encode("welcome", tracer_index=0, settings={"seed": 1}, scene=header.to_wire(),
                                 tree=tree.to_wire(), store_key="k", chunks=[0, 2])))
    back = SceneHeader.from_wire(msg.scene)
    assert np.array_equal(back.bounds, header.bounds) and back.camera == header.camera
    assert np.array_equal(ChunkTree.from_wire(msg.tree).boxes, tree.boxes)


def test_chunk_parts_reassemble_to_the_file(monkeypatch):
    monkeypatch.setattr(wire, "CHUNK_PART_BYTES", 1000)
    data = np.random.default_rng(3).integers(0, 256, 4321, dtype=np.uint8).tobytes()
    digest = hashlib.sha256(data).hexdigest()
    msgs = [decode(as_bytes(m)) for m in wire.chunk_parts(5, digest, data)]
    assert [m.part for m in msgs] == list(range(5)) and {m.parts for m in msgs} == {5}
    whole = b"".join(m.data.tobytes() for m in sorted(msgs, key=lambda m: m.offset))
    assert hashlib.sha256(whole).hexdigest() == digest == msgs[0].sha256


def test_describe_lists_every_message():
    text = wire.describe()
    for name in wire.MESSAGES:
        assert name in text


# -- validation: one case per rule ---------------------------------------------------
def _valid(msg_type="portal_rays", n=4, variant=0):
    frames = as_bytes(encode(msg_type, **sample_fields(msg_type, n, np.random.default_rng(0), variant)))
    return msgpack.unpackb(frames[0]), frames


def _index(header, name):
    return 1 + [e["name"] for e in header["arrays"]].index(name)


def _set_array(header, frames, name, array):
    """Replace one array, header entry and frame alike."""
    i = _index(header, name)
    header["arrays"][i - 1].update(dtype=array.dtype.str, shape=list(array.shape))
    frames[i] = array.tobytes()


def _poison(name, value, msg_type="portal_rays", variant=0, row=0):
    def edit(h, f):
        i = _index(h, name)
        a = np.frombuffer(f[i], np.dtype(h["arrays"][i - 1]["dtype"])).copy()
        a.reshape(h["arrays"][i - 1]["shape"][0], -1)[row, 0] = value
        f[i] = a.tobytes()
    return msg_type, variant, edit


def _header_edit(fn, msg_type="portal_rays", variant=0):
    return msg_type, variant, lambda h, f: fn(h)


def _copy_row(name, src, dst):
    """Row `dst` of array `name` made equal to row `src`."""
    def edit(h, f):
        i = _index(h, name)
        a = np.frombuffer(f[i], np.dtype(h["arrays"][i - 1]["dtype"])).copy()
        a[dst] = a[src]
        f[i] = a.tobytes()
    return edit


def _first_rows(n, *names):
    """Arrays `names` cut to their first n rows."""
    def edit(h, f):
        for name in names:
            i = _index(h, name)
            _set_array(h, f, name, np.frombuffer(f[i], np.dtype(h["arrays"][i - 1]["dtype"]))[:n].copy())
    return edit


def _drop_array(name):
    def edit(h, f):
        i = _index(h, name)
        del h["arrays"][i - 1], f[i]
    return edit


def _add_array(name, like):
    """A further array `name`, a copy of array `like` (as a peer with another record layout sends)."""
    def edit(h, f):
        i = _index(h, like)
        h["arrays"].append(dict(h["arrays"][i - 1], name=name))
        f.append(bytes(f[i]))
    return edit


CASES = {
    # (message type, variant, edit(header, frames)), words the error must contain
    "unknown type": (_header_edit(lambda h: h.update(type="teleport")), ["unknown message type", "teleport"]),
    "type not a str": (_header_edit(lambda h: h.update(type=3)), ["unknown message type"]),
    "wrong version": (_header_edit(lambda h: h.update(v=PROTOCOL_VERSION + 1)),
                      ["portal_rays", f"version {PROTOCOL_VERSION + 1}", f"version {PROTOCOL_VERSION}"]),
    "missing version": (_header_edit(lambda h: h.pop("v")), ["portal_rays", "None", f"version {PROTOCOL_VERSION}"]),
    "version not an int": (_header_edit(lambda h: h.update(v="1")),
                           ["portal_rays", "'1'", f"version {PROTOCOL_VERSION}"]),
    "missing field": (_header_edit(lambda h: h.pop("chunk")), ["portal_rays", "'chunk'", "missing"]),
    "extra field": (_header_edit(lambda h: h.update(colour="red")), ["portal_rays", "'colour'"]),
    "str for int": (_header_edit(lambda h: h.update(chunk="7")), ["portal_rays", "'chunk'", "int", "str"]),
    "bool for int": (_header_edit(lambda h: h.update(chunk=True)), ["portal_rays", "'chunk'", "bool"]),
    "int past int64": (_header_edit(lambda h: h.update(chunk=2**63)), ["portal_rays", "'chunk'"]),
    "negative int": (_header_edit(lambda h: h.update(chunk=-1)), ["portal_rays", "'chunk'", ">= 0"]),
    "float for int": (_header_edit(lambda h: h.update(eye_iteration=1.0), "eye_job"),
                      ["eye_job", "'eye_iteration'"]),
    "int for bool": (_header_edit(lambda h: h.update(has_store=1), "register"), ["register", "'has_store'"]),
    "bad struct": (_header_edit(lambda h: h["capacity"].pop("cores"), "register"), ["register", "'capacity'"]),
    "zero cores": (_header_edit(lambda h: h["capacity"].update(cores=0), "register"), ["register", "'capacity'"]),
    "bad list item": (_header_edit(lambda h: h["peers"][0].append(5), "peers"), ["peers", "'peers'"]),
    "bad choice": (_header_edit(lambda h: h.update(kind="neutrino"), "portal_rays"), ["portal_rays", "'kind'"]),
    "bad sha256": (_header_edit(lambda h: h.update(sha256="XYZ"), "chunk_data"), ["chunk_data", "'sha256'"]),
    "non-str key in data": (_header_edit(lambda h: h["status"].update({b"k": 1}), "heartbeat"),
                            ["heartbeat", "'status'"]),
    "arrays missing": (("portal_rays", 0, lambda h, f: (h.pop("arrays"), f.__delitem__(slice(1, None)))),
                       ["portal_rays", "'arrays'", "missing"]),
    "arrays not a list": (_header_edit(lambda h: h.update(arrays={})), ["portal_rays", "'arrays'", "list"]),
    "array entry malformed": (_header_edit(lambda h: h["arrays"][0].pop("shape")), ["portal_rays", "entry 0"]),
    "frame missing": (("portal_rays", 0, lambda h, f: f.pop()), ["portal_rays", "'arrays'", "lists 11 arrays"]),
    "extra frame": (("portal_rays", 0, lambda h, f: f.append(b"")), ["portal_rays", "12 array frames"]),
    "array missing": (("portal_rays", 0, lambda h, f: _drop_array("batch.rng")(h, f)),
                      ["portal_rays", "'batch.rng'", "missing"]),
    "unknown array": (("portal_rays", 0, lambda h, f: h["arrays"][0].update(name="batch.spin")),
                      ["portal_rays", "'batch.spin'", "not an array"]),
    # A tracer from before deposits lost their normal (version 8) still sending one.
    "deposit normal": (("results", 0, _add_array("deposits.normal", "deposits.incoming")),
                       ["results", "'deposits.normal'", "not an array"]),
    "duplicate array": (("portal_rays", 0, lambda h, f: h["arrays"][1].update(name=h["arrays"][0]["name"])),
                        ["portal_rays", "listed twice"]),
    "dtype mismatch": (("portal_rays", 0, lambda h, f: _set_array(h, f, "batch.origin", np.zeros((4, 3)))),
                       ["portal_rays", "'batch.origin'", "'<f8'", "'<f4'"]),
    "big-endian dtype": (("portal_rays", 0, lambda h, f: _set_array(h, f, "batch.rng", np.zeros(4, ">u8"))),
                         ["portal_rays", "'batch.rng'", "'>u8'"]),
    "wrong trailing dims": (("portal_rays", 0, lambda h, f: _set_array(h, f, "batch.origin",
                                                                      np.zeros((3, 4), np.float32))),
                            ["portal_rays", "'batch.origin'", "shape (3, 4)", "(n, 3)"]),
    "wrong rank": (("portal_rays", 0, lambda h, f: _set_array(h, f, "batch.pixel", np.zeros((4, 1), np.int32))),
                   ["portal_rays", "'batch.pixel'", "shape"]),
    "negative length": (("portal_rays", 0, lambda h, f: h["arrays"][0].update(shape=[-4, 3])),
                        ["portal_rays", "shape"]),
    "too large": (("portal_rays", 0, lambda h, f: h["arrays"][_index(h, "batch.job") - 1].update(shape=[1 << 40])),
                  ["portal_rays", "'batch.job'", "cap"]),
    "frame size": (("portal_rays", 0, lambda h, f: f.__setitem__(_index(h, "batch.job"),
                                                                f[_index(h, "batch.job")][:-1])),
                   ["portal_rays", "'batch.job'", "31 bytes", "needs 32"]),
    "unequal record lengths": (("portal_rays", 0, lambda h, f: _set_array(h, f, "batch.depth",
                                                                         np.zeros(3, np.int32))),
                               ["portal_rays", "'batch.depth'", "3 rows", "batch has 4"]),
    "fixed rows": (("portal_rays", 0, lambda h, f: _set_array(h, f, "cull_box", np.zeros((3, 3)))),
                   ["portal_rays", "'cull_box'", "3 rows"]),
    "NaN origin": (_poison("batch.origin", np.nan), ["portal_rays", "'batch.origin'", "NaN"]),
    "inf direction": (_poison("batch.direction", np.inf, row=3), ["portal_rays", "'batch.direction'", "infinite"]),
    "inf flux": (_poison("deposits.flux", -np.inf, "results"), ["results", "'deposits.flux'"]),
    "NaN hit position": (_poison("hits.position", np.nan, "results", variant=1), ["results", "'hits.position'"]),
    "NaN cull box": (_poison("cull_box", np.nan), ["portal_rays", "'cull_box'", "NaN"]),
    "malformed msgpack": (("portal_rays", 0, lambda h, f: f.__setitem__(0, b"\xc1\x00")), ["malformed msgpack"]),
    "truncated msgpack": (("portal_rays", 0, lambda h, f: f.__setitem__(0, f[0][:20])), ["malformed msgpack"]),
    "header not a map": (("portal_rays", 0, lambda h, f: f.__setitem__(0, msgpack.packb([1, 2]))),
                         ["header is a list", "not a map"]),
    "msgpack extension": (("portal_rays", 0, lambda h, f: f.__setitem__(0, msgpack.packb(msgpack.ExtType(5, b"x")))),
                          ["malformed msgpack", "extension"]),
    "empty message": (("portal_rays", 0, lambda h, f: f.clear()), ["empty message"]),
    "continuing paths reported": (_poison("ends", 3, "results"), ["results", "'ends'", "continuing"]),
    "negative end count": (_poison("ends", -1, "results", row=2), ["results", "'ends'", "negative"]),
    "hits without eye_iteration": (_header_edit(lambda h: h.update(eye_iteration=None), "results", 1),
                                   ["results", "'eye_iteration'"]),
    "photon package without box": (("portal_rays", 0, lambda h, f: _drop_array("cull_box")(h, f)),
                                   ["portal_rays", "'cull_box'"]),
    "eye package with box": (("portal_rays", 0, lambda h, f: h.update(kind="eye", eye_iteration=1)),
                             ["portal_rays", "'cull_box'", "eye and shadow rays"]),
    "shadow package with a ray batch": (("portal_rays", 1, lambda h, f: h.update(kind="shadow")),
                                        ["portal_rays", "'shadows'", "ShadowRays"]),
    "photon job of no photons": (_poison("counts", 0, "photon_job", row=2),
                                 ["photon_job", "'counts'", ">= 1"]),
    "photon job past the cap": (_poison("counts", wire.MAX_EMITTED, "photon_job"),
                                ["photon_job", "'counts'", f"at most {wire.MAX_EMITTED}"]),
    "photon job's job twice": (("photon_job", 0, _copy_row("job_ids", 0, 3)),
                               ["photon_job", "'job_ids'", "twice"]),
    "photon job's negative key": (_poison("rng_keys", -5, "photon_job", row=1), ["photon_job", "'rng_keys'"]),
    "photon job's negative id": (_poison("job_ids", -1, "photon_job"), ["photon_job", "'job_ids'"]),
    "photon job's credit for another job": (_poison("credit_job", 12345, "photon_job"),
                                            ["photon_job", "'credit_job'", "one term per job"]),
    "photon job's credit missing a job": (("photon_job", 0, _first_rows(3, "credit_job", "credit_exp")),
                                          ["photon_job", "'credit_job'", "one term per job"]),
    "photon job's unequal columns": (("photon_job", 0, lambda h, f: _set_array(h, f, "counts",
                                                                              np.ones(3, np.int64))),
                                     ["photon_job", "'counts'", "3 rows", "jobs has 4"]),
    "photon job's old batch": (("photon_job", 0, lambda h, f: h.update(chunk=1)),
                               ["photon_job", "'chunk'", "not part of the message"]),
    "photon job without a box": (("photon_job", 0, lambda h, f: _drop_array("cull_box")(h, f)),
                                 ["photon_job", "'cull_box'", "missing"]),
    "eye job of no pixels": (_poison("counts", 0, "eye_job", row=1), ["eye_job", "'counts'", ">= 1"]),
    "eye job past the cap": (_poison("counts", wire.MAX_EMITTED, "eye_job"),
                             ["eye_job", "'counts'", f"at most {wire.MAX_EMITTED}"]),
    "eye job's negative pixel": (_poison("pixel_starts", -4, "eye_job", row=2),
                                 ["eye_job", "'pixel_starts'"]),
    "eye job's negative id": (_poison("job_ids", -1, "eye_job"), ["eye_job", "'job_ids'"]),
    "eye job's tile twice": (("eye_job", 0, _copy_row("job_ids", 0, 3)), ["eye_job", "'job_ids'", "twice"]),
    "eye job's credit for another job": (_poison("credit_job", 12345, "eye_job"),
                                         ["eye_job", "'credit_job'", "one term per job"]),
    "eye job's credit missing a tile": (("eye_job", 0, _first_rows(3, "credit_job", "credit_exp")),
                                        ["eye_job", "'credit_job'", "one term per job"]),
    "eye job's unequal columns": (("eye_job", 0, lambda h, f: _set_array(h, f, "counts",
                                                                          np.ones(3, np.int64))),
                                  ["eye_job", "'counts'", "3 rows", "tiles has 4"]),
    "eye job's old batch": (("eye_job", 0, lambda h, f: h.update(chunk=1)),
                            ["eye_job", "'chunk'", "not part of the message"]),
    "eye job without an iteration": (_header_edit(lambda h: h.pop("eye_iteration"), "eye_job"),
                                     ["eye_job", "'eye_iteration'", "missing"]),
    "gather's jobs out of order": (("gather", 0, _copy_row("job_ids", 0, 3)), ["gather", "'job_ids'", "increasing"]),
    "gather's zero radius": (_poison("radius", 0.0, "gather", row=1), ["gather", "'radius'", "> 0"]),
    "gather's NaN box": (_poison("job_boxes", np.nan, "gather"), ["gather", "'job_boxes'", "NaN"]),
    "gather's unknown phase": (_header_edit(lambda h: h.update(phase="guess"), "gather"), ["gather", "'phase'"]),
    "pilot without a total": (_header_edit(lambda h: h.update(phase="pilot", total=0), "gather"),
                              ["gather", "'total'", "pilot"]),
    "epoch sums' negative count": (_poison("m", -1.0, "epoch_sums", row=2), ["epoch_sums", "'m'", ">= 0"]),
    "epoch sums' rows out of order": (("epoch_sums", 3, _copy_row("rows", 0, 3)),
                                      ["epoch_sums", "'rows'", "increasing"]),
    "epoch sums' flux of two": (("epoch_sums", 0, lambda h, f: _set_array(h, f, "flux", np.zeros(2))),
                                ["epoch_sums", "'flux'", "2 rows"]),
    "hit points without a version": (_header_edit(lambda h: h.pop("hits_version"), "hit_points"),
                                     ["hit_points", "'hits_version'", "missing"]),
    "part past parts": (_header_edit(lambda h: h.update(part=1), "chunk_data"), ["chunk_data", "'part'"]),
    "data past file": (_header_edit(lambda h: h.update(file_bytes=2), "chunk_data"),
                       ["chunk_data", "'data'", "file_bytes"]),
}


@pytest.mark.parametrize("case", sorted(CASES))
def test_each_malformed_message_is_refused_naming_type_and_field(case):
    (msg_type, variant, edit), words = CASES[case]
    header, frames = _valid(msg_type, variant=variant)
    edit(header, frames)
    if frames and case not in ("malformed msgpack", "truncated msgpack", "header not a map",
                               "msgpack extension"):
        frames[0] = msgpack.packb(header)
    with pytest.raises(WireError) as info:
        decode(frames)
    text = str(info.value)
    assert "\n" not in text and len(text) < 300
    for word in words:
        assert word in text, (case, text)


def test_infinite_cull_box_means_no_culling_and_is_accepted():
    box = np.array([[-np.inf] * 3, [np.inf] * 3])
    msg = decode(encode("portal_rays", kind="photon", chunk=0, cull_box=box, batch=RayBatch.empty(), **NO_CREDIT))
    assert np.isinf(msg.cull_box).all()


def test_decode_refuses_types_a_role_does_not_take():
    frames = encode("portal_rays", **sample_fields("portal_rays", 2, np.random.default_rng(0)))
    with pytest.raises(WireError, match="portal_rays: not accepted here"):
        decode(frames, accept={"register", "results"})


@pytest.mark.parametrize("fields, words", [
    (dict(batch=RayBatch(*(a.astype(np.float64) if a.dtype.kind == "f" else a
                           for a in RayBatch.empty().arrays().values()))), ["'batch.origin'", "<f8"]),
    (dict(batch=PhotonDeposits.empty()), ["'batch'", "RayBatch", "PhotonDeposits"]),
    (dict(batch=RayBatch.empty(), spin=1), ["unexpected field 'spin'"]),
    (dict(batch=RayBatch.empty(), chunk=np.int64(-1)), ["'chunk'", ">= 0"]),
    (dict(batch=RayBatch.empty(), chunk=None), ["'chunk'"]),
])
def test_encode_refuses_what_decode_would(fields, words):
    args = dict(kind="eye", eye_iteration=0, chunk=0) | fields
    with pytest.raises(WireError) as info:
        encode("portal_rays", **args)
    assert all(w in str(info.value) for w in ["portal_rays", *words]), str(info.value)


def test_encode_wants_both_emitted_arrays():
    with pytest.raises(WireError, match="'emitted_rgb' must come with 'emitted_pixels'"):
        encode("results", chunk=0, eye_iteration=0, ends=np.zeros(5, np.int64),
               job_ids=np.zeros(0, np.int64), job_fed=np.zeros(0, np.int64),
                          job_left=np.zeros(0, np.int64), credit_job=np.zeros(0, np.int64),
                          credit_exp=np.zeros(0, np.int64),
               emitted_pixels=np.zeros(2, np.int32))


def test_encode_takes_numpy_scalars_and_missing_nullable_fields():
    msg = decode(encode("register", tracer_id="t", capacity={"cores": 2, "memory_bytes": 10},
                        endpoint="tcp://x:1", has_store=np.bool_(False)))
    assert msg.store_key is None and msg.has_store is False
    assert decode(encode("portal_rays", kind="eye", chunk=np.int32(3), eye_iteration=np.uint64(1),
                         batch=RayBatch.empty(), **NO_CREDIT)).chunk == 3


# -- version mismatch ------------------------------------------------------------
FUTURE = PROTOCOL_VERSION + 1


def _register_from_the_future(version=FUTURE):
    header, frames = _valid("register")
    frames[0] = msgpack.packb(header | {"v": version})
    return frames


def test_version_mismatch_is_refused_with_a_reason_naming_both_versions():
    with pytest.raises(VersionMismatch) as info:
        decode(_register_from_the_future())
    assert (info.value.theirs, info.value.ours, info.value.msg_type) == (FUTURE, PROTOCOL_VERSION, "register")
    reply = decode(as_bytes(wire.error_reply(info.value)))
    assert reply.type == "refused"
    assert str(FUTURE) in reply.reason and str(PROTOCOL_VERSION) in reply.reason and "version" in reply.reason


def test_refused_and_error_are_readable_across_versions():
    for msg_type in ("refused", "error"):
        header, frames = _valid(msg_type)
        frames[0] = msgpack.packb(header | {"v": 99})
        msg = decode(frames)
        assert msg.type == msg_type and msg.version == 99
    header, frames = _valid("shutdown")
    frames[0] = msgpack.packb(header | {"v": 99})
    with pytest.raises(VersionMismatch):
        decode(frames)


def test_other_errors_reply_with_an_error_message():
    header, frames = _valid("results")
    frames[0] = msgpack.packb(header | {"job": "x"})
    with pytest.raises(WireError) as info:
        decode(frames)
    reply = decode(wire.error_reply(info.value))
    assert reply.type == "error" and reply.about == "results" and "'job'" in reply.reason


# -- fuzz: damage never escapes as anything but WireError --------------------------
def _decode_or_wire_error(frames):
    try:
        return decode(frames)
    except WireError:
        return None


@settings(max_examples=400, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(data=st.data(), msg_type=st.sampled_from(sorted(wire.MESSAGES)), variant=st.integers(0, 3))
def test_random_damage_raises_only_wire_error(data, msg_type, variant):
    frames = as_bytes(encode(msg_type, **sample_fields(msg_type, data.draw(st.integers(0, 5)),
                                                       np.random.default_rng(0), variant)))
    for _ in range(data.draw(st.integers(1, 4))):
        op = data.draw(st.sampled_from(["flip", "truncate", "extend", "drop", "add", "swap", "garbage"]))
        if not frames and op != "add":
            continue
        i = data.draw(st.integers(0, len(frames) - 1)) if frames else 0
        f = bytearray(frames[i]) if frames else bytearray()
        if op == "flip" and f:
            j = data.draw(st.integers(0, len(f) - 1))
            f[j] ^= data.draw(st.integers(1, 255))
        elif op == "truncate":
            f = f[:data.draw(st.integers(0, len(f)))]
        elif op == "extend":
            f += data.draw(st.binary(max_size=16))
        elif op == "garbage":
            f = bytearray(data.draw(st.binary(max_size=64)))
        if op == "drop":
            del frames[i]
        elif op == "add":
            frames.insert(i, data.draw(st.binary(max_size=32)))
        elif op == "swap" and len(frames) > 1:
            j = data.draw(st.integers(0, len(frames) - 1))
            frames[i], frames[j] = frames[j], frames[i]
        elif frames:
            frames[i] = bytes(f)
    _decode_or_wire_error(frames)


_msgpack_values = st.recursive(
    st.none() | st.booleans() | st.integers(-2**63, 2**64 - 1) | st.floats() | st.text(max_size=8)
    | st.binary(max_size=8),
    lambda inner: st.lists(inner, max_size=4) | st.dictionaries(st.text(max_size=6), inner, max_size=4),
    max_leaves=12)


@settings(max_examples=300, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(data=st.data(), msg_type=st.sampled_from(sorted(wire.MESSAGES)), value=_msgpack_values)
def test_random_header_values_raise_only_wire_error(data, msg_type, value):
    header, frames = _valid(msg_type, n=2)
    key = data.draw(st.sampled_from(sorted(header) + ["new"]))
    if key == "arrays" and header["arrays"] and data.draw(st.booleans()):
        entry = data.draw(st.sampled_from(header["arrays"]))
        entry[data.draw(st.sampled_from(["name", "dtype", "shape"]))] = value
    else:
        header[key] = value
    frames[0] = msgpack.packb(header)
    _decode_or_wire_error(frames)
