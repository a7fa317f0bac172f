"""The one array codec: how a numpy array is written into msgpack, on the
wire and on disk, and read back checked. No pickle.

    pack(a)                 -> {"dtype": "<f4", "shape": [n, 3], "data": raw bytes}
    unpack(d)               -> the array of a packed dict, checked
    frame(a)                -> (dtype str, shape list, memoryview of the bytes):
                               for formats that carry the bytes apart
                               (the wire's frames, services/wire.py)
    from_bytes(b, dtype, shape) -> the array over raw bytes `b`, checked
    raw(a, dtype)           -> the raw bytes of `a` as `dtype`, for formats
                               whose dtypes are fixed and shapes implied
                               (chunk tree, portals, chunk files)

A dtype is a numpy dtype string from DTYPES: little-endian ("<f4", "<i8")
or one byte ("|u1", "|b1"). Object, string, structured and big-endian
dtypes never decode: the bytes come from files and peers we do not trust,
and only plain numbers can be read from bytes without running anything.
Every failed check raises ArrayError, one line that starts with `what`.

Decoded arrays are views of the bytes (read-only when they are `bytes`),
except that a misaligned view is copied: numba's kernels want aligned
arrays, and small frames sit at odd offsets in libzmq's receive buffer.
`copy=True` always copies (a writable array the caller owns).
"""
from __future__ import annotations

import math

import numpy as np

DTYPES = frozenset({"|b1", "|i1", "|u1", "<i2", "<u2", "<i4", "<u4", "<i8", "<u8", "<f2", "<f4", "<f8"})
KEYS = ("dtype", "shape", "data")


class ArrayError(ValueError):
    """An array that cannot be encoded or decoded; one line naming it."""


def _little(a: np.ndarray, what: str) -> np.ndarray:
    """`a` contiguous, little-endian, of an allowed dtype."""
    a = a if a.flags.c_contiguous else np.ascontiguousarray(a)   # which makes a 0-d array 1-d
    if a.dtype.byteorder == ">":
        a = a.astype(a.dtype.newbyteorder("<"))
    if a.dtype.str not in DTYPES:
        raise ArrayError(f"{what}: dtype {a.dtype.str!r} cannot be encoded (only {_listed()})")
    return a


def _listed() -> str:
    return ", ".join(sorted(DTYPES))


def pack(a, what: str = "array") -> dict:
    """{"dtype", "shape", "data"} of `a`: the map every msgpack document of
    the project holds an array as (scene header, ledger, checkpoint)."""
    a = _little(np.asarray(a), what)
    return {"dtype": a.dtype.str, "shape": list(a.shape), "data": a.tobytes()}


def is_packed(v) -> bool:
    """True for a map that `pack` made (a document's arrays among its
    other fields)."""
    return type(v) is dict and len(v) == len(KEYS) and all(k in v for k in KEYS)


def unpack(d, dtype: str | None = None, shape: tuple | None = None, what: str = "array",
           copy: bool = False) -> np.ndarray:
    """The array of a packed map, checked; `dtype` and `shape`, when
    given, are what the format expects."""
    if not is_packed(d):
        raise ArrayError(f"{what}: not a packed array (a map of {', '.join(KEYS)})")
    return from_bytes(d["data"], d["dtype"], d["shape"], what, copy, dtype, shape)


def frame(a, what: str = "array") -> tuple[str, list, memoryview]:
    """(dtype, shape, the bytes) of `a` without copying a contiguous
    little-endian array: the bytes travel in a frame of their own."""
    a = _little(np.asarray(a), what)
    # A flat byte view: memoryview.cast refuses shapes with a 0 in them.
    return a.dtype.str, list(a.shape), memoryview(a.reshape(-1).view(np.uint8))


def raw(a, dtype: str) -> bytes:
    """The bytes of `a` as `dtype` (converted, C order)."""
    if dtype not in DTYPES:
        raise ArrayError(f"raw bytes: dtype {dtype!r} is not one of {_listed()}")
    return np.ascontiguousarray(a, dtype).tobytes()


def from_bytes(data, dtype, shape, what: str = "array", copy: bool = False,
               expect_dtype: str | None = None, expect_shape: tuple | None = None) -> np.ndarray:
    """The array of `dtype` and `shape` over the raw bytes `data` (bytes,
    memoryview, zmq frame), checked against each other and the allow-list."""
    _check_dtype(dtype, what, expect_dtype)
    shape = _check_shape(shape, what, expect_shape)
    buf = _byte_view(data, what)
    need = math.prod(shape) * np.dtype(dtype).itemsize
    if buf.nbytes != need:
        raise ArrayError(f"{what}: has {buf.nbytes} bytes, shape {shape} of {dtype} needs {need}")
    a = np.frombuffer(buf, dtype).reshape(shape)
    return a.copy() if copy or not a.flags.aligned else a


def _check_dtype(dtype, what: str, expect: str | None) -> None:
    if type(dtype) is not str or dtype not in DTYPES:
        shown = repr(dtype[:20]) if type(dtype) is str else type(dtype).__name__
        raise ArrayError(f"{what}: dtype {shown} is not one of {_listed()}")
    if expect is not None and dtype != expect:
        raise ArrayError(f"{what}: has dtype {dtype!r}, expected {expect!r}")


def _check_shape(shape, what: str, expect: tuple | None) -> tuple:
    if type(shape) not in (list, tuple) or not all(type(s) is int and s >= 0 for s in shape):
        raise ArrayError(f"{what}: shape {str(shape)[:60]} is not a list of ints >= 0")
    shape = tuple(shape)
    if expect is not None and shape != tuple(expect):
        raise ArrayError(f"{what}: has shape {shape[:8]}, expected {tuple(expect)}")
    return shape


def _byte_view(data, what: str) -> memoryview:
    try:
        buf = memoryview(data)
    except TypeError:
        raise ArrayError(f"{what}: data is a {type(data).__name__}, not bytes") from None
    return buf.cast("B") if buf.ndim != 1 or buf.format != "B" else buf
