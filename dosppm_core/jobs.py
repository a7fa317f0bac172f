"""Job records: the arrays that move between the steps of the pipeline.

The same records serve single-process SPPM, out-of-core OSPPM and the
distributed service; only the transport between steps differs. Every
record is a bundle of equally long numpy arrays, so it can be sliced,
concatenated and framed for the wire without conversion.
"""
from __future__ import annotations

from dataclasses import dataclass, fields

import numpy as np
from numba import njit

# Why a path ended, as counted per step (the server's exact accounting).
CONTINUES, ESCAPED, ABSORBED, MAX_DEPTH, STORED = 0, 1, 2, 3, 4
END_NAMES = ("continues", "escaped", "absorbed", "max_depth", "stored")


class _Record:
    """Struct-of-arrays helpers shared by all records."""

    def __len__(self) -> int:
        # The first field's name, looked up once per class: dataclasses.fields
        # costs microseconds, and the server takes len() of every part it routes.
        cls = type(self)
        name = cls.__dict__.get("_first_field")
        if name is None:
            name = fields(self)[0].name
            setattr(cls, "_first_field", name)
        return int(getattr(self, name).shape[0])

    # Columns a record may lack (None): only scenes that need them carry
    # them, and every helper here keeps them absent (`HitPoints.frame`).
    OPTIONAL: frozenset = frozenset()

    def take(self, index, replace: dict | None = None) -> "_Record":
        """Rows at `index` (an integer array or a boolean mask), with the
        columns in `replace` (name: full-length array) taken from there
        instead. np.take is ~4x faster than fancy indexing on (n, 3) rows."""
        index = np.asarray(index)
        if index.dtype == np.bool_:
            index = np.flatnonzero(index)
        replace = replace or {}
        out = {}
        for f in fields(self):
            a = replace.get(f.name, getattr(self, f.name))
            out[f.name] = None if a is None else np.take(a, index, axis=0)
        return type(self)(**out)

    def slice(self, start: int, stop: int) -> "_Record":
        """Rows [start, stop) as views, no copy."""
        cols = {f.name: getattr(self, f.name) for f in fields(self)}
        return type(self)(**{k: None if a is None else a[start:stop] for k, a in cols.items()})

    def partition(self, keys: np.ndarray, rows: np.ndarray | None = None,
                  replace: dict | None = None) -> dict:
        """{key: the rows with that key}, with one permuting copy of the
        record in all (views of it per key), in row order within a key;
        `rows` (with `keys` as long) partitions only those rows, `replace`
        as in `take`. Rays mostly stay in their chunk, so a single key
        costs no copy."""
        if len(keys) == 0:
            return {}
        lo, hi = int(keys.min()), int(keys.max())
        if lo == hi and rows is None and not replace:
            return {lo: self}
        if hi - lo < _COUNTING_SORT_KEYS:
            order, cuts = _counting_order(keys, lo, hi - lo + 1)
        else:
            order = np.argsort(keys, kind="stable")
            cuts = np.searchsorted(keys[order], np.arange(lo, hi + 2))
        whole = self.take(order if rows is None else rows[order], replace)
        return {lo + b: whole.slice(cuts[b], cuts[b + 1])
                for b in range(len(cuts) - 1) if cuts[b + 1] > cuts[b]}

    @classmethod
    def concat(cls, parts: list) -> "_Record":
        parts = [p for p in parts if p is not None]
        if not parts:
            return cls.empty()
        if len(parts) == 1:
            return parts[0]     # records are not changed in place: no copy needed
        return cls(**{f.name: cls._concat_column(f.name, parts) for f in fields(cls)})

    @classmethod
    def _concat_column(cls, name: str, parts: list):
        """One column of `concat`. An optional column absent from every part
        stays absent; absent from some, those parts' rows get zeros."""
        cols = [getattr(p, name) for p in parts]
        if all(c is None for c in cols):
            return None
        dtype, shape = cls.SCHEMA[name]
        return np.concatenate([np.zeros((len(p),) + shape, dtype) if c is None else c
                               for p, c in zip(parts, cols)])

    def arrays(self) -> dict:
        return {f.name: getattr(self, f.name) for f in fields(self)}

    @classmethod
    def empty(cls) -> "_Record":
        return cls(**{name: None if name in cls.OPTIONAL else np.empty((0,) + shape, dtype)
                      for name, (dtype, shape) in cls.SCHEMA.items()})


# Keys spanning fewer values than this are sorted by counting (chunk ids,
# tracer ids): 3x faster than a stable argsort.
_COUNTING_SORT_KEYS = 1 << 16


@njit(cache=True)
def _counting_order(keys, lo, span):
    """(stable order of the rows by key, cuts: key lo + b's rows are
    order[cuts[b]:cuts[b + 1]])."""
    cuts = np.zeros(span + 1, np.int64)
    for i in range(keys.shape[0]):
        cuts[keys[i] - lo + 1] += 1
    for b in range(span):
        cuts[b + 1] += cuts[b]
    fill = cuts[:-1].copy()
    order = np.empty(keys.shape[0], np.int64)
    for i in range(keys.shape[0]):
        b = keys[i] - lo
        order[fill[b]] = i
        fill[b] += 1
    return order, cuts


@dataclass
class RayBatch(_Record):
    """Paths in flight. Photon paths carry flux in `weight` and pixel -1;
    eye paths carry the camera weight and their pixel. `rng` is each path's
    own counter-based state, so a path traces the same wherever it goes."""
    origin: np.ndarray      # float32 (n, 3)
    direction: np.ndarray   # float32 (n, 3), unit
    weight: np.ndarray      # float32 (n, 3)
    pixel: np.ndarray       # int32 (n,)
    depth: np.ndarray       # int32 (n,): surfaces hit so far
    rng: np.ndarray         # uint64 (n,)
    # Distance along the ray already searched in earlier chunks: a ray
    # continued through a portal keeps its origin and skips [0, tmin).
    tmin: np.ndarray = None  # float32 (n,); None means zeros (a new ray)
    # The job each path belongs to, so packages of many jobs can be traced
    # as one batch and their ended paths still be counted per job (the
    # server's exact accounting). None means zeros.
    job: np.ndarray = None   # int64 (n,)

    SCHEMA = {"origin": (np.float32, (3,)), "direction": (np.float32, (3,)),
              "weight": (np.float32, (3,)), "pixel": (np.int32, ()),
              "depth": (np.int32, ()), "rng": (np.uint64, ()), "tmin": (np.float32, ()),
              "job": (np.int64, ())}

    def __post_init__(self):
        if self.tmin is None:
            self.tmin = np.zeros(self.origin.shape[0], np.float32)
        if self.job is None:
            self.job = np.zeros(self.origin.shape[0], np.int64)


@dataclass
class PhotonDeposits(_Record):
    """Photons stored on non-specular surfaces. `incoming` points back
    toward where the photon came from. No surface normal: a photon counts
    by the side of the hit point gathering it, as in pbrt-v4."""
    position: np.ndarray    # float32 (n, 3)
    incoming: np.ndarray    # float32 (n, 3)
    flux: np.ndarray        # float32 (n, 3)
    # The photon job that deposited it: a job's deposits count only once
    # all its paths have ended (exactly-once accounting). None means zeros.
    job: np.ndarray = None  # int64 (n,)

    SCHEMA = {"position": (np.float32, (3,)), "incoming": (np.float32, (3,)),
              "flux": (np.float32, (3,)), "job": (np.int64, ())}

    def __post_init__(self):
        if self.job is None:
            self.job = np.zeros(self.position.shape[0], np.int64)


@dataclass
class HitPoints(_Record):
    """Where eye paths met their first non-specular surface. `normal`
    faces `outgoing` (toward the camera along the path)."""
    position: np.ndarray    # float32 (n, 3)
    normal: np.ndarray      # float32 (n, 3)
    outgoing: np.ndarray    # float32 (n, 3)
    weight: np.ndarray      # float32 (n, 3): camera path throughput
    material: np.ndarray    # int32 (n,)
    pixel: np.ndarray       # int32 (n,)
    # The lobe of a hit point on an anisotropic rough conductor, or one with
    # textured roughness: its tangent s (3) and alpha_u, alpha_v there
    # (`kernels.anisotropic.hit_point_frames`; zeros at other hit points),
    # so the gather weighs photons by the BSDF direct light uses. None in
    # a scene without such a material: other scenes carry nothing.
    frame: np.ndarray = None  # float32 (n, 5)

    SCHEMA = {"position": (np.float32, (3,)), "normal": (np.float32, (3,)),
              "outgoing": (np.float32, (3,)), "weight": (np.float32, (3,)),
              "material": (np.int32, ()), "pixel": (np.int32, ()), "frame": (np.float32, (5,))}
    OPTIONAL = frozenset({"frame"})


@dataclass
class ShadowRays(_Record):
    """The direct-light ray of each hit point (next-event estimation). It
    continues its eye path (same pixel, same job) and ends it, counted
    STORED like a hit point without one. Two kinds, by `pdf`:

    - pdf 0, a shadow ray to a point sampled on a light: if nothing lies
      before `tmax` it adds `radiance` to its pixel;
    - pdf > 0, a BSDF-sampled ray of a glossy hit point (multiple
      importance sampling, `kernels.direct`): `tmax` is infinite, and if
      its first hit is the front of an emitting triangle it adds
      radiance * Le / (c_light p_light + pdf) there."""
    origin: np.ndarray      # float32 (n, 3), off the hit point's surface
    direction: np.ndarray   # float32 (n, 3), unit
    radiance: np.ndarray    # float32 (n, 3): the contribution (or its factor) if unoccluded
    tmax: np.ndarray        # float32 (n,): distance to the light point (inf: to the first hit)
    pdf: np.ndarray         # float32 (n,): 0, or c_bsdf times the BSDF's solid-angle pdf
    pixel: np.ndarray       # int32 (n,)
    tmin: np.ndarray = None  # float32 (n,): searched in earlier chunks (as RayBatch)
    job: np.ndarray = None   # int64 (n,): the eye job

    SCHEMA = {"origin": (np.float32, (3,)), "direction": (np.float32, (3,)),
              "radiance": (np.float32, (3,)), "tmax": (np.float32, ()), "pdf": (np.float32, ()),
              "pixel": (np.int32, ()), "tmin": (np.float32, ()), "job": (np.int64, ())}

    def __post_init__(self):
        if self.tmin is None:
            self.tmin = np.zeros(self.origin.shape[0], np.float32)
        if self.job is None:
            self.job = np.zeros(self.origin.shape[0], np.int64)


def paths_per_job(fed: list[np.ndarray], left: list[np.ndarray]):
    """(job ids, paths fed in, paths that left) of a tracing step, from the
    `job` columns of the batches in and of those leaving through portals.
    Paths are conserved: fed - left of them ended in the step. Reporting
    both lets the server count each job's open path segments: a segment
    is closed by the very message that carries its deposits, so a job
    whose segments are all closed has all its deposits in hand too."""
    fed_ids, fed_n = np.unique(np.concatenate(fed) if fed else np.empty(0, np.int64), return_counts=True)
    left_n = np.zeros_like(fed_n)
    if left and sum(len(x) for x in left):
        left_ids, counts = np.unique(np.concatenate(left), return_counts=True)
        at = np.searchsorted(fed_ids, left_ids)
        if np.any(at >= len(fed_ids)) or np.any(fed_ids[np.minimum(at, len(fed_ids) - 1)] != left_ids):
            raise ValueError("paths left that were never fed in")
        left_n[at] = counts
    return fed_ids.astype(np.int64), fed_n.astype(np.int64), left_n.astype(np.int64)
