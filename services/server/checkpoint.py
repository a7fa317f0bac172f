"""Server checkpoints: the pixel statistics, the counters that go with them
and the render settings, so a render survives a server restart
(`dosppm server --resume DIR`, `dosppm render --resume DIR`).

    DIR/checkpoint.msgpack   one msgpack map (no pickle):
        format "dosppm-checkpoint", version, store_key, settings {},
        next_job, next_eye_iteration, counters {}, sha256 (of the arrays),
        arrays {name: {dtype, shape, data (raw little-endian bytes)}}

Written atomically: a temporary file in DIR, fsync, rename over the old
one, fsync of DIR; a crash leaves the previous checkpoint whole. What is
saved is what the statistics hold (photons applied, N_e, N, R, tau, the
emission seen), never jobs in flight: on resume those are simply not
there, and the job and eye-iteration counters go on past every id ever
used, so no photon is traced twice into the same image.

    DIR/job-ids.msgpack      format "dosppm-job-ids", claimed: the first
        job id of the last server resumed from DIR

Each server run makes job ids in a block of its own (ID_BLOCK ids from
its first): the tracers may still hold, and go on sending, messages of
jobs the killed server made after its last checkpoint, and those must
never be taken for the resumed server's jobs (claim_job_ids).
"""
from __future__ import annotations

import hashlib
import os

import msgpack
import numpy as np

from dosppm_core import arrays as codec

FORMAT, VERSION = "dosppm-checkpoint", 1
FILE = "checkpoint.msgpack"
IDS_FILE, IDS_FORMAT = "job-ids.msgpack", "dosppm-job-ids"
ID_BLOCK = 1 << 40       # job ids per server run: 10^12 jobs of 1024 photons
ARRAYS = ("photon_count", "radius", "tau", "emission")


class CheckpointError(ValueError):
    """A missing, corrupt or foreign checkpoint; one line naming file and field."""


def _digest(arrays: dict) -> str:
    h = hashlib.sha256()
    for name in ARRAYS:
        h.update(name.encode())
        h.update(np.ascontiguousarray(arrays[name]).tobytes())
    return h.hexdigest()


def write(directory: str, stats, meta: dict) -> str:
    """Save `stats` (PixelStatistics; the caller holds its lock) with
    `meta` (store_key, settings, next_job, next_eye_iteration, counters)."""
    os.makedirs(directory, exist_ok=True)
    arrays = {name: np.asarray(getattr(stats, name), "<f8") for name in ARRAYS}
    doc = dict(meta, format=FORMAT, version=VERSION, width=stats.width, height=stats.height,
               alpha=stats.alpha, eye_iterations=stats.eye_iterations,
               photons_emitted=int(stats.photons_emitted), sha256=_digest(arrays),
               arrays={n: codec.pack(a) for n, a in arrays.items()})
    path = os.path.join(directory, FILE)
    _write_atomically(directory, path, msgpack.packb(doc, use_bin_type=True))
    return path


def _write_atomically(directory: str, path: str, data: bytes) -> None:
    """A temporary file, fsync, rename over `path`, fsync of the directory."""
    tmp = f"{path}.tmp-{os.getpid()}"
    with open(tmp, "wb") as f:
        f.write(data)
        f.flush()
        os.fsync(f.fileno())
    os.replace(tmp, path)
    fd = os.open(directory, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def read(directory: str, store_key: str | None = None) -> dict:
    """The checkpoint in `directory`, checked; arrays as numpy. Raises
    CheckpointError naming the file and what is wrong."""
    path = os.path.join(directory, FILE)
    try:
        with open(path, "rb") as f:
            doc = msgpack.unpackb(f.read(), raw=False, strict_map_key=True)
    except FileNotFoundError:
        raise CheckpointError(f"{path}: no checkpoint here") from None
    except Exception as e:   # msgpack raises many types on garbage: all mean corrupt
        raise CheckpointError(f"{path}: unreadable (corrupt or truncated): {type(e).__name__}") from None
    if type(doc) is not dict or doc.get("format") != FORMAT:
        raise CheckpointError(f"{path}: field 'format' is not {FORMAT!r} (not a dosppm checkpoint)")
    if doc.get("version") != VERSION:
        raise CheckpointError(f"{path}: field 'version' is {doc.get('version')!r}, this program reads {VERSION}")
    for key in ("store_key", "settings", "next_job", "next_eye_iteration", "counters", "width", "height",
                "alpha", "eye_iterations", "photons_emitted", "sha256", "arrays"):
        if key not in doc:
            raise CheckpointError(f"{path}: field {key!r} missing")
    if store_key is not None and doc["store_key"] != store_key:
        raise CheckpointError(f"{path}: field 'store_key' is {doc['store_key']!r}: a checkpoint of another "
                              f"scene or chunking (this render's is {store_key!r})")
    doc["arrays"] = _arrays(path, doc)
    if _digest(doc["arrays"]) != doc["sha256"]:
        raise CheckpointError(f"{path}: field 'sha256' does not match the arrays (corrupt)")
    return doc


def _arrays(path: str, doc: dict) -> dict:
    n = int(doc["width"]) * int(doc["height"])
    want = {"photon_count": (n,), "radius": (n,), "tau": (n, 3), "emission": (n, 3)}
    out = {}
    for name, shape in want.items():
        a = doc["arrays"].get(name) if type(doc["arrays"]) is dict else None
        try:
            out[name] = codec.unpack(a, "<f8", shape, f"{path}: array {name!r} is malformed", copy=True)
        except codec.ArrayError as e:
            raise CheckpointError(str(e)) from None
    return out


def restore(stats, doc: dict) -> None:
    """Put a checkpoint's statistics into a fresh PixelStatistics."""
    if (stats.width, stats.height) != (doc["width"], doc["height"]):
        raise CheckpointError(f"checkpoint is {doc['width']}x{doc['height']}, this render is "
                              f"{stats.width}x{stats.height}")
    for name, a in doc["arrays"].items():
        setattr(stats, name, a)
    stats.alpha = float(doc["alpha"])
    stats.eye_iterations = int(doc["eye_iterations"])
    stats.photons_emitted = int(doc["photons_emitted"])


def claim_job_ids(directory: str, doc: dict) -> int:
    """The first job id of a server resuming from the checkpoint `doc` in
    `directory`: the block after those of the server that wrote it and of
    every server resumed from this directory before, recorded (atomically)
    before any job is made, so a second resume from the same checkpoint
    gets a block of its own too."""
    path = os.path.join(directory, IDS_FILE)
    claimed = max(int(doc.get("first_job", 0)), _last_claim(path))
    first = (claimed // ID_BLOCK + 1) * ID_BLOCK
    _write_atomically(directory, path, msgpack.packb({"format": IDS_FORMAT, "claimed": first}))
    return first


def _last_claim(path: str) -> int:
    """The first job id the job-id file at `path` records (0 if none)."""
    try:
        with open(path, "rb") as f:
            ids = msgpack.unpackb(f.read(), raw=False)
    except FileNotFoundError:
        return 0
    except Exception as e:   # msgpack raises many types on garbage: all mean corrupt
        raise CheckpointError(f"{path}: unreadable (corrupt or truncated): {type(e).__name__}") from None
    if type(ids) is not dict or ids.get("format") != IDS_FORMAT or type(ids.get("claimed")) is not int:
        raise CheckpointError(f"{path}: field 'claimed' missing or not an integer (not a dosppm job-id claim)")
    return ids["claimed"]
