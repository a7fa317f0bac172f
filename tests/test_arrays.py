"""The one array codec (dosppm_core/arrays.py, issue 34): round trips of
every dtype it allows, one-line errors on malformed input, and every format
that uses it still writing the bytes the code before it wrote (the
"legacy" encoders below are that code, frozen) and reading them back."""
from __future__ import annotations

import msgpack
import numpy as np
import pytest

from dosppm_core import arrays
from dosppm_core.arrays import ArrayError
from dosppm_core.chunks.store import Portals
from dosppm_core.chunks.tree import ChunkTree
from dosppm_core.scene.builtin import cornell_box
from dosppm_core.scene.model import SceneHeader
from dosppm_core.sppm.statistics import PixelStatistics
from services import ledger, wire
from services.server import checkpoint
from tests.helpers.chunks import uniform_tree

SHAPES = [(), (0,), (5,), (3, 4), (2, 0, 3), (2, 2, 3)]


def _legacy_pack(a):
    """What model.py, ledger.py and checkpoint.py each wrote before the codec."""
    a = np.ascontiguousarray(a)
    return {"dtype": a.dtype.str, "shape": list(a.shape), "data": a.tobytes()}


def _sample(dtype: str, shape) -> np.ndarray:
    rng = np.random.default_rng(7)
    if dtype == "|b1":
        return rng.integers(0, 2, shape).astype(bool)
    return (rng.normal(size=shape) * 100).astype(dtype)


@pytest.mark.parametrize("shape", SHAPES)
@pytest.mark.parametrize("dtype", sorted(arrays.DTYPES))
def test_every_allowed_dtype_and_shape_round_trips(dtype, shape):
    a = _sample(dtype, shape)
    doc = msgpack.unpackb(msgpack.packb(arrays.pack(a)))
    back = arrays.unpack(doc)
    assert back.dtype == a.dtype and back.shape == a.shape and back.tobytes() == a.tobytes()
    dt, sh, buf = arrays.frame(a)
    assert arrays.from_bytes(bytes(buf), dt, sh).tobytes() == a.tobytes()
    assert arrays.from_bytes(arrays.raw(a, dtype), dtype, shape).tobytes() == a.tobytes()


def test_pack_writes_the_frozen_bytes():
    a = np.arange(3, dtype="<i4")
    frozen = bytes.fromhex("83a56474797065a33c6934a5736861706591""03a464617461c40c000000000100000002000000")
    assert msgpack.packb(arrays.pack(a)) == frozen == msgpack.packb(_legacy_pack(a))


def test_big_endian_input_is_written_little_endian():
    a = np.arange(4, dtype=">f8")
    d = arrays.pack(a)
    assert d["dtype"] == "<f8" and np.array_equal(arrays.unpack(d), a)


def test_decoded_views_are_aligned_and_copy_gives_a_writable_array():
    a = np.arange(6, dtype="<f8")
    odd = memoryview(b"x" + a.tobytes())[1:]
    got = arrays.from_bytes(odd, "<f8", [6])
    assert got.flags.aligned and np.array_equal(got, a)
    view = arrays.unpack(arrays.pack(a))
    assert not view.flags.writeable and arrays.unpack(arrays.pack(a), copy=True).flags.writeable


@pytest.mark.parametrize("doc, words", [
    ({"dtype": "<f4", "shape": [3], "data": b"\0" * 11}, ["11 bytes", "needs 12"]),
    ({"dtype": "|O", "shape": [1], "data": b"\0" * 8}, ["'|O'", "not one of"]),
    ({"dtype": "<U4", "shape": [1], "data": b"\0" * 16}, ["'<U4'"]),
    ({"dtype": ">f8", "shape": [1], "data": b"\0" * 8}, ["'>f8'"]),
    ({"dtype": "<c16", "shape": [1], "data": b"\0" * 16}, ["'<c16'"]),
    ({"dtype": "V8", "shape": [1], "data": b"\0" * 8}, ["'V8'"]),
    ({"dtype": 4, "shape": [1], "data": b"\0" * 4}, ["dtype int"]),
    ({"dtype": "<f4", "shape": [-1], "data": b""}, ["shape", ">= 0"]),
    ({"dtype": "<f4", "shape": "3", "data": b"\0" * 12}, ["shape"]),
    ({"dtype": "<f4", "shape": [True], "data": b"\0" * 4}, ["shape"]),
    ({"dtype": "<f4", "shape": [1], "data": 5}, ["data is a int"]),
    ({"dtype": "<f4", "shape": [1]}, ["not a packed array"]),
    ([1, 2], ["not a packed array"]),
])
def test_malformed_input_is_one_line_naming_it(doc, words):
    with pytest.raises(ArrayError) as info:
        arrays.unpack(doc, what="thing 'x'")
    text = str(info.value)
    assert "\n" not in text and text.startswith("thing 'x': ")
    assert all(w in text for w in words), text


def test_expected_dtype_and_shape_are_enforced():
    d = arrays.pack(np.zeros((2, 3)))
    with pytest.raises(ArrayError, match="dtype '<f8', expected '<f4'"):
        arrays.unpack(d, "<f4")
    with pytest.raises(ArrayError, match=r"shape \(2, 3\), expected \(3, 2\)"):
        arrays.unpack(d, "<f8", (3, 2))


def test_object_and_string_arrays_are_never_encoded():
    for a in (np.array([object()]), np.array(["text"]), np.zeros(2, complex)):
        with pytest.raises(ArrayError, match="cannot be encoded"):
            arrays.pack(a)
    with pytest.raises(ArrayError):
        arrays.raw(np.zeros(2), "|O")


# -- the formats that use the codec -----------------------------------------------
def _legacy_value(v):
    return _legacy_pack(v) if isinstance(v, np.ndarray) else (list(v) if isinstance(v, tuple) else v)


def test_scene_header_writes_the_legacy_bytes_and_reads_them():
    header = cornell_box().header()
    wired = header.to_wire()
    legacy = dict(wired, bounds=_legacy_pack(header.bounds),
                  materials={k: _legacy_value(v) for k, v in vars(header.materials).items()},
                  lights={k: _legacy_value(v) for k, v in header.lights.wire_fields().items()},
                  textures={k: _legacy_value(v) for k, v in vars(header.textures).items()})
    assert msgpack.packb(wired) == msgpack.packb(legacy)
    back = SceneHeader.from_wire(msgpack.unpackb(msgpack.packb(legacy)))
    assert np.array_equal(back.materials.reflectance, header.materials.reflectance)
    assert back.materials.reflectance.flags.writeable and back.materials.two_sided.dtype == np.bool_


def test_chunk_tree_and_portals_write_the_legacy_bytes_and_read_them():
    tree = uniform_tree([[0, 0, 0], [1, 1, 1]], (3, 2, 1))
    legacy_tree = {"axis": tree.axis.astype("<i1").tobytes(), "split": tree.split.astype("<f8").tobytes(),
                   "child": tree.child.astype("<i4").tobytes(), "boxes": tree.boxes.astype("<f8").tobytes(),
                   "nodes": int(tree.axis.shape[0]), "chunks": tree.chunk_count}
    assert msgpack.packb(tree.to_wire()) == msgpack.packb(legacy_tree)
    back = ChunkTree.from_wire(legacy_tree)
    assert np.array_equal(back.boxes, tree.boxes) and back.child.dtype == np.int32
    p = Portals.of_tree(tree)
    legacy = {"count": len(p), "chunk_a": p.chunk_a.astype("<i4").tobytes(),
              "chunk_b": p.chunk_b.astype("<i4").tobytes(), "axis": p.axis.astype("<i1").tobytes(),
              "plane": p.plane.astype("<f8").tobytes(), "lo": p.lo.astype("<f8").tobytes(),
              "hi": p.hi.astype("<f8").tobytes(), "root_box": p.root_box.astype("<f8").tobytes()}
    assert msgpack.packb(p.to_wire()) == msgpack.packb(legacy)
    assert Portals.from_wire(legacy).same_as(p)
    with pytest.raises(ValueError, match="portals 'lo': has 8 bytes"):
        Portals.from_wire(dict(legacy, lo=b"\0" * 8))


def _stats(w=3, h=2):
    stats = PixelStatistics(w, h, 0.01)
    rng = np.random.default_rng(1)
    for name in checkpoint.ARRAYS:
        setattr(stats, name, rng.random(np.shape(getattr(stats, name))))
    return stats


def test_checkpoint_writes_the_legacy_bytes_and_reads_them(tmp_path):
    stats = _stats()
    meta = dict(store_key="k", settings={}, next_job=3, next_eye_iteration=1, counters={})
    checkpoint.write(str(tmp_path), stats, meta)
    doc = msgpack.unpackb((tmp_path / checkpoint.FILE).read_bytes())
    legacy = dict(doc, arrays={n: _legacy_pack(np.asarray(getattr(stats, n), "<f8"))
                               for n in checkpoint.ARRAYS})
    assert (tmp_path / checkpoint.FILE).read_bytes() == msgpack.packb(legacy, use_bin_type=True)
    read = checkpoint.read(str(tmp_path))
    assert all(np.array_equal(read["arrays"][n], getattr(stats, n)) for n in checkpoint.ARRAYS)
    legacy["arrays"]["tau"]["data"] = legacy["arrays"]["tau"]["data"][:-8]
    (tmp_path / checkpoint.FILE).write_bytes(msgpack.packb(legacy, use_bin_type=True))
    with pytest.raises(checkpoint.CheckpointError, match="array 'tau' is malformed: has 136 bytes") as e:
        checkpoint.read(str(tmp_path))
    assert "\n" not in str(e.value) and checkpoint.FILE in str(e.value)


def test_ledger_records_keep_the_legacy_encoding():
    keys, paths = np.arange(4, dtype=np.uint64), np.full(4, 1024, np.int64)
    boxes = np.zeros((4, 2, 3))
    book = ledger.Ledger.__new__(ledger.Ledger)
    book.path, book.records, book.count, book._file = None, [], 0, None

    class Update:
        kind, photons_emitted, jobs = "photons", 4096, (keys, paths, boxes)
    book.record(Update)
    rec = book.records[0]
    legacy = {"kind": "photons", "emitted": 4096, "keys": _legacy_pack(keys), "paths": _legacy_pack(paths),
              "boxes": _legacy_pack(boxes)}
    assert msgpack.packb(rec) == msgpack.packb(legacy)


def test_the_wire_reports_a_short_frame_through_the_codec():
    from tests.test_wire import sample_fields
    frames = [bytes(f) for f in wire.encode("portal_rays", **sample_fields("portal_rays", 4,
                                                                           np.random.default_rng(0)))]
    header = msgpack.unpackb(frames[0])
    i = next(k for k, e in enumerate(header["arrays"]) if e["name"] == "batch.job") + 1
    frames[i] = frames[i][:-1]
    with pytest.raises(wire.WireError, match=r"portal_rays: field 'batch.job': has 31 bytes, .* needs 32"):
        wire.decode(frames)
