"""The generic codec beneath `services.wire`: how a message type is
declared (scalar field types, array groups, `Spec`) and how a declared
message becomes frames and back, with every check that holds for any
message (types, dtypes, shapes, sizes, finiteness). It knows no message:
the table of messages, the protocol version and the per-message rules
live in services/wire.py, the one module the rest imports the protocol
from (nothing else imports this one). The framing is described there.
"""
from __future__ import annotations

import re
from dataclasses import dataclass, field
from functools import cached_property

import msgpack
import numpy as np

from dosppm_core import arrays

MAX_ELEMENTS = 1 << 28           # per array: sanity cap on a declared size
RESERVED = ("v", "type", "arrays")   # header keys that are no field


class WireError(ValueError):
    """A message that cannot be encoded or accepted; one line naming the
    message type and field. `prefix` is the sender's envelope, when known."""

    def __init__(self, text: str, msg_type: str | None = None, field: str | None = None):
        super().__init__(text)
        self.msg_type, self.field = msg_type, field
        self.prefix: list = []


# -- scalar field types ---------------------------------------------------------
class FieldType:
    label = "?"

    def ok(self, v) -> bool:
        raise NotImplementedError


class Int(FieldType):
    """An int that fits numpy's int64 (ids and counts end up in arrays)."""

    def __init__(self, minimum: int = 0):
        self.minimum, self.label = minimum, f"int >= {minimum}"

    def ok(self, v) -> bool:   # bool is an int to Python, never to the wire
        return type(v) is int and self.minimum <= v < 2**63


class Of(FieldType):
    def __init__(self, label: str, *types):
        self.label, self.types = label, types

    def ok(self, v) -> bool:
        return type(v) in self.types


class Hex(FieldType):
    label = "64 lowercase hex digits"

    def ok(self, v) -> bool:
        return type(v) is str and re.fullmatch(r"[0-9a-f]{64}", v) is not None


class Choice(FieldType):
    def __init__(self, *values):
        self.values, self.label = values, " or ".join(map(repr, values))

    def ok(self, v) -> bool:
        return type(v) is str and v in self.values


class Nullable(FieldType):
    def __init__(self, inner: FieldType):
        self.inner, self.label = inner, f"{inner.label} or None"

    def ok(self, v) -> bool:
        return v is None or self.inner.ok(v)


class ListOf(FieldType):
    def __init__(self, item: FieldType):
        self.item, self.label = item, f"list of {item.label}"

    def ok(self, v) -> bool:
        return type(v) is list and all(self.item.ok(x) for x in v)


class Struct(FieldType):
    def __init__(self, **members: FieldType):
        self.members = members
        self.label = "{" + ", ".join(f"{k}: {t.label}" for k, t in members.items()) + "}"

    def ok(self, v) -> bool:
        return (type(v) is dict and set(v) == set(self.members)
                and all(t.ok(v[k]) for k, t in self.members.items()))


class Data(FieldType):
    """A msgpack map of plain data (str keys; None, bool, int, float, str,
    bytes, lists, maps), to be read by its own from_wire. Walked without
    recursion: nesting depth is the sender's choice."""
    label = "map of plain data"
    PLAIN = (type(None), bool, int, float, str, bytes)

    def ok(self, v) -> bool:
        if type(v) is not dict:
            return False
        stack = [v]
        while stack:
            x = stack.pop()
            if type(x) is dict:
                if any(type(k) is not str for k in x):
                    return False
                stack.extend(x.values())
            elif type(x) is list:
                stack.extend(x)
            elif type(x) not in self.PLAIN:
                return False
        return True


INT, STR, BOOL, DATA = Int(0), Of("str", str), Of("bool", bool), Data()


# -- array groups ---------------------------------------------------------------
FINITE, NOT_NAN = "finite", "not NaN"


@dataclass(frozen=True)
class Column:
    wire: str            # name in the header's "arrays" list
    key: str             # the record field, or the message field for plain arrays
    dtype: np.dtype
    trailing: tuple
    values: str | None   # FINITE, NOT_NAN or None (no check)
    optional: bool = False   # a record's column it may lack (`_Record.OPTIONAL`)


@dataclass(frozen=True)
class Group:
    """Arrays that travel together with one leading length: a record (its
    columns rebuild `record`), or plain arrays that become message fields."""
    name: str
    columns: tuple
    record: type | None = None
    rows: int | None = None       # a fixed leading length, or any length
    optional: bool = False

    @property
    def keys(self) -> tuple:
        """The message fields this group fills."""
        return (self.name,) if self.record else tuple(c.key for c in self.columns)


def _le(dtype) -> np.dtype:
    return np.dtype(dtype).newbyteorder("<")   # "|u1" stays "|u1"


def record(name: str, cls, optional: bool = False) -> Group:
    """A record group from the class's SCHEMA; every float column finite."""
    cols = tuple(Column(f"{name}.{col}", col, _le(dt), tuple(shape),
                        FINITE if np.dtype(dt).kind == "f" else None, col in cls.OPTIONAL)
                 for col, (dt, shape) in cls.SCHEMA.items())
    return Group(name, cols, record=cls, optional=optional)


def plain(name: str, *cols, rows: int | None = None, optional: bool = False) -> Group:
    """Plain arrays: (field name, dtype, trailing shape, values check)."""
    return Group(name, tuple(Column(k, k, _le(dt), tuple(tr), v) for k, dt, tr, v in cols),
                 rows=rows, optional=optional)


# -- message specs --------------------------------------------------------------
@dataclass(frozen=True)
class Spec:
    name: str
    route: str                            # who sends it to whom (documentation)
    fields: dict                          # scalar field -> FieldType
    groups: tuple = ()
    check: object = None                  # fields -> error text naming a field, or None
    any_version: bool = False             # frozen forever: decodes under any version
    defaults: dict = field(default_factory=dict)   # encode fills these when omitted

    @cached_property
    def array_names(self) -> frozenset:
        return frozenset(c.wire for g in self.groups for c in g.columns)


def shape_text(rows, trailing) -> str:
    return str(("n" if rows is None else rows,) + tuple(trailing)).replace("'", "")


# -- encode ---------------------------------------------------------------------
_MISSING = object()


def _plain_scalar(v):
    """numpy scalars and tuples are easy to pass by accident; msgpack takes neither."""
    if isinstance(v, np.generic):
        return v.item()
    return list(v) if isinstance(v, tuple) else v


def _group_columns(spec: Spec, g: Group, given: dict) -> dict | None:
    """{wire name: array} for one group from encode's arguments, or None if
    an optional group is absent."""
    if g.record:
        rec = given.pop(g.name, None)
        if rec is None:
            return None
        if not isinstance(rec, g.record):
            raise WireError(f"{spec.name}: field {g.name!r} must be a {g.record.__name__}, "
                            f"got {type(rec).__name__}", spec.name, g.name)
        # An optional column the record lacks is left out of the message.
        return {c.wire: getattr(rec, c.key) for c in g.columns
                if not (c.optional and getattr(rec, c.key) is None)}
    cols = {c.wire: given.pop(c.key, None) for c in g.columns}
    present = [k for k, a in cols.items() if a is not None]
    if not present:
        return None
    if len(present) < len(cols):
        missing = next(k for k, a in cols.items() if a is None)
        raise WireError(f"{spec.name}: field {missing!r} must come with {present[0]!r}", spec.name, missing)
    return cols


def _frame_of(spec: Spec, c: Column, a) -> tuple[dict, memoryview]:
    a = np.asarray(a)
    if a.dtype != c.dtype:
        raise WireError(f"{spec.name}: array {c.wire!r} has dtype {a.dtype.str}, the wire wants "
                        f"{c.dtype.str}", spec.name, c.wire)
    dtype, shape, buf = arrays.frame(a)   # no copy of the records' own arrays
    return {"name": c.wire, "dtype": dtype, "shape": shape}, buf


def pack(spec: Spec, header: dict, given: dict) -> list:
    """[header bytes, array memoryviews...] for one message of `spec`:
    `header` holds the envelope ("v", "type"), `given` the fields
    (consumed). Scalars absent take the spec's defaults; the rules are
    checked by the caller (`wire.encode` decodes what it made)."""
    for k in spec.fields:
        header[k] = _plain_scalar(given.pop(k)) if k in given else spec.defaults.get(k, _MISSING)
    entries, frames = [], []
    for g in spec.groups:
        cols = _group_columns(spec, g, given)
        for c in g.columns if cols is not None else ():
            if c.wire not in cols:
                continue
            entry, frame = _frame_of(spec, c, cols[c.wire])
            entries.append(entry)
            frames.append(frame)
    if given:
        raise WireError(f"{spec.name}: unexpected field {sorted(given)[0]!r}", spec.name, sorted(given)[0])
    header["arrays"] = entries
    header = {k: v for k, v in header.items() if v is not _MISSING}
    try:
        head = msgpack.packb(header, use_bin_type=True)
    except (TypeError, ValueError, OverflowError) as e:
        raise WireError(f"{spec.name}: cannot encode the header: {e}", spec.name) from None
    return [head, *frames]


# -- decode ---------------------------------------------------------------------
def _fail(spec_name: str, field_: str | None, text: str):
    where = f"field {field_!r} " if field_ else ""
    raise WireError(f"{spec_name}: {where}{text}", spec_name, field_)


def _show(v) -> str:
    """A bad value for an error line: short scalars as themselves."""
    if isinstance(v, (bool, int, float, type(None))) or (isinstance(v, (str, bytes)) and len(v) <= 40):
        return f"{type(v).__name__} {v!r}"
    return type(v).__name__


def _ext_refused(code, data):
    raise ValueError(f"msgpack extension type {code} is not part of the protocol")


def read_header(frame) -> dict:
    try:
        header = msgpack.unpackb(frame, raw=False, strict_map_key=True, use_list=True,
                                 ext_hook=_ext_refused, timestamp=0)
    except Exception as e:   # msgpack raises a zoo of types on garbage; all mean "malformed"
        raise WireError(f"malformed msgpack header: {type(e).__name__}: {e}"[:200]) from None
    if type(header) is not dict:
        raise WireError(f"header is a {type(header).__name__}, not a map")
    return header


def _check_scalars(spec: Spec, header: dict) -> dict:
    expected = set(spec.fields) | set(RESERVED)
    for k in header:
        if k not in expected:
            _fail(spec.name, str(k)[:60], "is not part of the message")
    out = {}
    for k, t in spec.fields.items():
        if k not in header:
            _fail(spec.name, k, "is missing")
        if not t.ok(header[k]):
            _fail(spec.name, k, f"must be {t.label}, got {_show(header[k])}")
        out[k] = header[k]
    if "arrays" not in header:
        _fail(spec.name, "arrays", "is missing")
    return out


def _array_entries(spec: Spec, header: dict, nframes: int) -> dict:
    """{wire name: (dtype str, shape, frame index)} from the header."""
    entries = header["arrays"]
    if type(entries) is not list:
        _fail(spec.name, "arrays", "must be a list")
    if len(entries) != nframes - 1:
        _fail(spec.name, "arrays", f"lists {len(entries)} arrays but {nframes - 1} array frames follow")
    out = {}
    for i, e in enumerate(entries):
        if not (type(e) is dict and set(e) == {"name", "dtype", "shape"} and type(e["name"]) is str
                and type(e["dtype"]) is str and type(e["shape"]) is list
                and all(type(s) is int for s in e["shape"])):
            _fail(spec.name, "arrays", f"entry {i} is not {{name: str, dtype: str, shape: [int]}}")
        if e["name"] not in spec.array_names:
            _fail(spec.name, e["name"][:60], "is not an array of this message")
        if e["name"] in out:
            _fail(spec.name, e["name"][:60], "is listed twice")
        out[e["name"]] = (e["dtype"], e["shape"], i + 1)
    return out


def _check_column(spec: Spec, c: Column, dtype: str, shape: list, frame) -> np.ndarray:
    if dtype != c.dtype.str:
        _fail(spec.name, c.wire, f"has dtype {dtype[:20]!r}, expected {c.dtype.str!r}")
    if len(shape) != 1 + len(c.trailing) or tuple(shape[1:]) != c.trailing or shape[0] < 0:
        _fail(spec.name, c.wire, f"has shape {tuple(shape[:8])}, expected {shape_text(None, c.trailing)}")
    count = shape[0] * int(np.prod(c.trailing, dtype=np.int64))   # Python ints: no overflow
    if count > MAX_ELEMENTS:
        _fail(spec.name, c.wire, f"declares {shape[:4]}: over the cap of {MAX_ELEMENTS} elements")
    try:
        return arrays.from_bytes(frame, dtype, shape, f"{spec.name}: field {c.wire!r}")
    except arrays.ArrayError as e:
        raise WireError(str(e), spec.name, c.wire) from None


def _check_values(spec: Spec, c: Column, a: np.ndarray) -> None:
    if c.values == FINITE and not np.isfinite(a).all():
        _fail(spec.name, c.wire, "holds NaN or infinite values")
    if c.values == NOT_NAN and np.isnan(a).any():
        _fail(spec.name, c.wire, "holds NaN values")


def _decode_group(spec: Spec, g: Group, entries: dict, frames, check_values: bool) -> dict:
    present = [c.wire for c in g.columns if c.wire in entries]
    if not present and g.optional:
        return dict.fromkeys(g.keys)
    missing = [c.wire for c in g.columns if c.wire not in entries and not c.optional]
    if missing:
        _fail(spec.name, missing[0], "is missing from the arrays")
    cols = {}
    for c in g.columns:
        if c.wire not in entries:
            continue        # an optional column left out: the record gets None
        dtype, shape, i = entries.pop(c.wire)
        cols[c] = _check_column(spec, c, dtype, shape, frames[i])
    lengths = {c.wire: a.shape[0] for c, a in cols.items()}
    want = g.rows if g.rows is not None else next(iter(lengths.values()))
    for name, n in lengths.items():
        if n != want:
            _fail(spec.name, name, f"has {n} rows, {g.name} has {want}")
    for c, a in cols.items():
        if check_values:
            _check_values(spec, c, a)
    if g.record:
        return {g.name: g.record(**{c.key: a for c, a in cols.items()})}
    return {c.key: a for c, a in cols.items()}


def read_fields(spec: Spec, header: dict, frames, check_values: bool = True) -> dict:
    """The fields of a message of `spec` (its header read, its type and
    version accepted): scalars, plain arrays (views of the frames) and
    records, each checked; the spec's own `check` is the caller's."""
    out = _check_scalars(spec, header)
    entries = _array_entries(spec, header, len(frames))
    for g in spec.groups:
        out.update(_decode_group(spec, g, entries, frames, check_values))
    return out
