"""Triangle sources: a scene's triangles read in blocks, so that subdivision
can stream a scene larger than its own memory budget.

A source is a `SceneHeader` plus `count` triangles with global ids 0..count-1,
read as blocks of (first id, corners float32 (m, 3, 3), material int32 (m,)).
`SceneSource` wraps a `Scene` in memory; on-disk sources (`soupfile`) memory-map
their arrays and never hold more than one block.
"""
from __future__ import annotations

import hashlib
from typing import Iterator, Protocol

import msgpack
import numpy as np

from dosppm_core.scene.model import Scene, SceneHeader

BLOCK = 1 << 20


class TriangleSource(Protocol):
    header: SceneHeader
    count: int

    def blocks(self, size: int = BLOCK) -> Iterator[tuple[int, np.ndarray, np.ndarray]]:
        """(first global id, corners (m, 3, 3) float32, material (m,) int32)."""

    def content_hash(self) -> str:
        """Hex digest of the triangles, materials and header: equal sources
        (and only they) give equal hashes."""


class SceneSource:
    """A `Scene` held in memory, as a triangle source."""

    def __init__(self, scene: Scene):
        self.scene = scene
        self.header = scene.header()
        self.count = scene.triangle_count

    def blocks(self, size: int = BLOCK):
        s = self.scene
        for start in range(0, self.count, size):
            tris = s.triangles[start:start + size]
            yield start, np.take(s.vertices, tris, axis=0), s.tri_material[start:start + size]

    @property
    def has_uv(self) -> bool:
        return len(self.scene.uvs) > 0

    def corner_uv(self, first: int, count: int) -> np.ndarray:
        """(count, 3, 2) float32 texture coordinates of the corners of
        triangles [first, first + count) (a source with `has_uv`)."""
        return np.take(self.scene.uvs, self.scene.triangles[first:first + count], axis=0)

    @property
    def has_normals(self) -> bool:
        return len(self.scene.normals) > 0

    def corner_normals(self, first: int, count: int) -> np.ndarray:
        """(count, 3, 3) float32 vertex normals of the corners of triangles
        [first, first + count) (a source with `has_normals`: smooth meshes)."""
        return np.take(self.scene.normals, self.scene.triangles[first:first + count], axis=0)

    def content_hash(self) -> str:
        h = hashlib.sha256()
        s = self.scene
        for a in (s.vertices, s.triangles, s.tri_material) + ((s.uvs,) if len(s.uvs) else ()) \
                + ((s.normals,) if len(s.normals) else ()):
            h.update(np.ascontiguousarray(a).tobytes())
        h.update(header_digest(self.header))
        return h.hexdigest()


def header_digest(header: SceneHeader) -> bytes:
    """Bytes that change whenever anything in the header does."""
    return hashlib.sha256(msgpack.packb(header.to_wire())).digest()
