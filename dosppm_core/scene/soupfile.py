"""The triangle-soup directory: a scene too big to hold in memory, on disk.

    DIR/soup.msgpack   {"format": "dosppm-soup", "version": 1, "count": n,
                        "header": SceneHeader.to_wire(), "hash": hex}
    DIR/corners.f32    float32 (n, 3, 3), little-endian, raw
    DIR/material.i32   int32 (n,), little-endian, raw

Raw arrays (not .npy) so that the writer can append blocks without knowing n
in advance, and readers read them block by block at an offset. Not memory-
mapped: every page a scan touches would stay mapped, so a reader's resident
memory would grow to the file's size (issue 17 measured 1.7x the scene
while subdividing), while a read block is freed when the next replaces it. The manifest is written last, under
a temporary name renamed into place, so an interrupted writer leaves a
directory that `open_soup` refuses.
"""
from __future__ import annotations

import hashlib
import os

import msgpack
import numpy as np

from dosppm_core.scene.model import SceneError, SceneHeader
from dosppm_core.scene.soup import BLOCK, header_digest

FORMAT, VERSION = "dosppm-soup", 1
MANIFEST, CORNERS, MATERIAL = "soup.msgpack", "corners.f32", "material.i32"


class SoupWriter:
    """Append triangle blocks, then `close(header)`. The content hash covers
    the triangles, the materials and the header."""

    def __init__(self, path: str):
        self.path = path
        os.makedirs(path, exist_ok=True)
        for name in (MANIFEST, CORNERS, MATERIAL):
            if os.path.exists(os.path.join(path, name)):
                os.remove(os.path.join(path, name))
        self._corners = open(os.path.join(path, CORNERS), "wb")
        self._material = open(os.path.join(path, MATERIAL), "wb")
        self._hash = hashlib.sha256()
        self.count = 0
        self.lo = np.full(3, np.inf)
        self.hi = np.full(3, -np.inf)

    def append(self, corners: np.ndarray, material: np.ndarray) -> None:
        corners = np.ascontiguousarray(corners, "<f4").reshape(-1, 3, 3)
        material = np.ascontiguousarray(material, "<i4").reshape(-1)
        if len(corners) != len(material):
            raise ValueError("corners and material differ in length")
        if len(corners):
            if not np.all(np.isfinite(corners)):
                raise SceneError(f"{self.path}: NaN or Inf vertex in triangles "
                                 f"{self.count}..{self.count + len(corners) - 1}")
            flat = corners.reshape(-1, 3)   # min over one axis: 3x faster than over (0, 1)
            self.lo = np.minimum(self.lo, flat.min(axis=0))
            self.hi = np.maximum(self.hi, flat.max(axis=0))
        for f, a in ((self._corners, corners), (self._material, material)):
            b = a.tobytes()
            f.write(b)
            self._hash.update(b)
        self.count += len(corners)

    def close(self, header: SceneHeader) -> str:
        """Finish; returns the content hash."""
        self._corners.close()
        self._material.close()
        self._hash.update(header_digest(header))
        digest = self._hash.hexdigest()
        doc = {"format": FORMAT, "version": VERSION, "count": self.count,
               "header": header.to_wire(), "hash": digest}
        tmp = os.path.join(self.path, MANIFEST + ".tmp")
        with open(tmp, "wb") as f:
            f.write(msgpack.packb(doc))
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, os.path.join(self.path, MANIFEST))
        return digest


class SoupSource:
    """A soup directory as a `TriangleSource`, read one block at a time."""

    def __init__(self, path: str, header: SceneHeader, count: int, digest: str):
        self.path, self.header, self.count, self._hash = path, header, count, digest

    def blocks(self, size: int = BLOCK):
        with open(os.path.join(self.path, CORNERS), "rb") as fc, \
                open(os.path.join(self.path, MATERIAL), "rb") as fm:
            for start in range(0, self.count, size):
                m = min(size, self.count - start)
                corners = np.fromfile(fc, "<f4", 9 * m)
                material = np.fromfile(fm, "<i4", m)
                if len(material) != m or len(corners) != 9 * m:
                    raise SceneError(f"{self.path}: the soup ends inside triangles {start}..{start + m - 1} "
                                     f"of {self.count} (truncated while open)")
                yield (start, corners.reshape(m, 3, 3).astype(np.float32, copy=False),
                       material.astype(np.int32, copy=False))

    def content_hash(self) -> str:
        return self._hash


def is_soup(path: str) -> bool:
    return os.path.isdir(path) and os.path.exists(os.path.join(path, MANIFEST))


def open_soup(path: str) -> SoupSource:
    """Open a soup directory; a missing, foreign or truncated one raises
    SceneError naming the file."""
    manifest = os.path.join(path, MANIFEST)
    try:
        with open(manifest, "rb") as f:
            doc = msgpack.unpackb(f.read())
    except (OSError, ValueError, msgpack.ExtraData) as e:
        raise SceneError(f"{manifest}: cannot read soup manifest: {e}") from None
    if not isinstance(doc, dict) or doc.get("format") != FORMAT:
        raise SceneError(f"{manifest}: not a dosppm triangle soup")
    if doc.get("version") != VERSION:
        raise SceneError(f"{manifest}: soup version {doc.get('version')!r}, expected {VERSION}")
    count = int(doc["count"])
    for name, itemsize in ((CORNERS, 36), (MATERIAL, 4)):
        full = os.path.join(path, name)
        size = os.path.getsize(full) if os.path.exists(full) else -1
        if size != count * itemsize:
            raise SceneError(f"{full}: {size} bytes, expected {count * itemsize} "
                             f"for {count} triangles (truncated or foreign)")
    header = SceneHeader.from_wire(doc["header"])
    return SoupSource(path, header, count, doc["hash"])
