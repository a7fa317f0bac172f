"""The chunk store: a subdivided scene on disk, one file per chunk (§4.1).

    DIR/manifest.msgpack   written last; everything below is described here
    DIR/chunk-0000.bin     chunk 0's raw arrays, little-endian, each at a
    DIR/chunk-0001.bin     64-byte-aligned offset given in the manifest:
    ...                      vertices float32 (nv, 3), triangles int32 (nt, 3),
                             tri_material int32 (nt,), global_id int32 (nt,),
                             and, if its triangles are textured, uv float32 (nv, 2),
                             if any is smooth, normals float32 (nv, 3) (`kernels.smooth`),
                             and the textures they read (the store's header
                             keeps only their sizes): tex_ids int32 (k,),
                             tex_info int32 (k, 6), tex_uv float64 (k, 6),
                             texels float32 (n, 3) (`scene.textures`)

The manifest (msgpack, no pickle) holds: format "dosppm-chunks", version,
the store key, the chunk tree (`ChunkTree.to_wire`), the portals, the scene
header (materials, lights, camera, render settings), the source's content
hash and triangle count, the budget, grid and forced chunk count it was made
with, and per chunk: file name, triangle and vertex counts, the (offset,
nbytes) of each array, the file size, the estimated memory when loaded
(arrays + Embree's copy and BVH) and the SHA-256 of the whole file.

The checksum covers the whole file: it is computed for free while writing
and checked by `load` (which reads the whole file anyway; SHA-256 runs at
over 1 GB/s, far faster than the BVH build that follows). `open` checks
only sizes, so opening a store of many gigabytes costs milliseconds.

A store is built in `DIR.partial-<pid>` and renamed into place once its
manifest is on disk, so an interrupted subdivision leaves nothing that
`ChunkStore.open` accepts under DIR.
"""
from __future__ import annotations

import hashlib
import os
import shutil
from dataclasses import dataclass

import msgpack
import numpy as np

from dosppm_core import arrays
from dosppm_core.chunks.tree import ChunkTree
from dosppm_core.scene.model import SceneError, SceneHeader

FORMAT, FORMAT_VERSION = "dosppm-chunks", 1
MANIFEST = "manifest.msgpack"
ALIGN = 64
# (name, dtype, columns; 0 = a plain vector), in file order.
ARRAYS = (("vertices", "<f4", 3), ("triangles", "<i4", 3),
          ("tri_material", "<i4", 0), ("global_id", "<i4", 0))
# Present only in the chunks of textured scenes: the vertices' texture
# coordinates, and the textures the chunk's triangles read (their ids in
# the scene's table, info rows, to_uv maps, texels). A chunk without them
# is laid out exactly as before, so old stores read unchanged.
UV_ARRAY = ("uv", "<f4", 2)
NORMAL_ARRAY = ("normals", "<f4", 3)     # in the chunks of scenes with smooth meshes only
TEXTURE_ARRAYS = (("tex_ids", "<i4", 0), ("tex_info", "<i4", 6), ("tex_uv", "<f8", 6),
                  ("texels", "<f4", 3))


def _arrays(uv: bool, textures: int = 0, normals: bool = False) -> tuple:
    return ARRAYS + ((UV_ARRAY,) if uv else ()) + ((NORMAL_ARRAY,) if normals else ()) \
        + (TEXTURE_ARRAYS if textures else ())


def _rows(vertices: int, textures: int, texels: int) -> dict:
    """Rows of each array not counted in triangles."""
    return {"vertices": vertices, "uv": vertices, "normals": vertices, "tex_ids": textures, "tex_info": textures,
            "tex_uv": textures, "texels": texels}


@dataclass
class ChunkGeometry:
    """One chunk's triangles, chunk-local; `global_id` maps to the source."""
    vertices: np.ndarray     # float32 (nv, 3)
    triangles: np.ndarray    # int32 (nt, 3)
    tri_material: np.ndarray  # int32 (nt,)
    global_id: np.ndarray    # int32 (nt,)
    uv: np.ndarray = None    # float32 (nv, 2), or (0, 2): an untextured chunk
    # The textures its triangles read, as in a `TextureTable` (ids: their
    # rows in the scene's); empty when it reads none or the chunk was cut
    # in memory (the scene header's table holds them then).
    tex_ids: np.ndarray = None   # int32 (k,)
    tex_info: np.ndarray = None  # int32 (k, 6)
    tex_uv: np.ndarray = None    # float64 (k, 6)
    texels: np.ndarray = None    # float32 (n, 3)
    normals: np.ndarray = None   # float32 (nv, 3), or (0, 3): no smooth mesh in the chunk's scene

    def __post_init__(self):
        for name, dtype, cols in (UV_ARRAY, NORMAL_ARRAY) + TEXTURE_ARRAYS:
            if getattr(self, name) is None:
                setattr(self, name, np.zeros((0, cols) if cols else 0, dtype))

    @property
    def nbytes(self) -> int:
        return sum(a.nbytes for a in (self.vertices, self.triangles, self.tri_material, self.global_id,
                                      self.uv, self.tex_ids, self.tex_info, self.tex_uv, self.texels,
                                      self.normals))

    @property
    def texture_bytes(self) -> int:
        return int(self.tex_ids.nbytes + self.tex_info.nbytes + self.tex_uv.nbytes + self.texels.nbytes)


class StoreError(ValueError):
    """A missing, corrupt or foreign chunk store; one line naming the path
    and the field or file at fault."""


def chunk_file_name(k: int) -> str:
    return f"chunk-{k:04d}.bin"


# -- portals -------------------------------------------------------------------
_OTHER = ((1, 2), (0, 2), (0, 1))   # the two axes spanning a face normal to axis a


# Portals.to_wire's raw arrays: (field, dtype, shape for n records), in order.
_PORTAL_ARRAYS = (("chunk_a", "<i4", lambda n: (n,)), ("chunk_b", "<i4", lambda n: (n,)),
                  ("axis", "|i1", lambda n: (n,)), ("plane", "<f8", lambda n: (n,)),
                  ("lo", "<f8", lambda n: (n, 2)), ("hi", "<f8", lambda n: (n, 2)),
                  ("root_box", "<f8", lambda n: (2, 3)))


@dataclass
class Portals:
    """The shared faces between neighbouring chunks (§4.1, stage 3).

    Record i is the rectangle where the upper face (along `axis[i]`) of chunk
    `chunk_a[i]` meets the lower face of chunk `chunk_b[i]`, at coordinate
    `plane[i]`; `lo[i]`, `hi[i]` span it in the two other axes, in increasing
    order (axis x: y, z; axis y: x, z; axis z: x, y). A face bordering several
    chunks (a T-junction) gives one record per neighbour."""
    chunk_a: np.ndarray   # int32 (p,)  the lower side
    chunk_b: np.ndarray   # int32 (p,)  the upper side
    axis: np.ndarray      # int8 (p,)
    plane: np.ndarray     # float64 (p,)
    lo: np.ndarray        # float64 (p, 2)
    hi: np.ndarray        # float64 (p, 2)
    root_box: np.ndarray  # float64 (2, 3)

    def __len__(self) -> int:
        return int(self.chunk_a.shape[0])

    @classmethod
    def of_tree(cls, tree: ChunkTree) -> "Portals":
        """Every pair of chunk boxes touching across a face of positive area.
        Chunk boxes share split values bit for bit, so touching is equality."""
        b = tree.boxes
        rows = []
        for a in range(3):
            u, v = _OTHER[a]
            for i in range(tree.chunk_count):
                js = np.flatnonzero(b[:, 0, a] == b[i, 1, a])
                lo = np.maximum(b[js, 0][:, (u, v)], b[i, 0, (u, v)])
                hi = np.minimum(b[js, 1][:, (u, v)], b[i, 1, (u, v)])
                ok = np.all(hi > lo, axis=1)
                rows += [(i, j, a, b[i, 1, a], *l, *h) for j, l, h in zip(js[ok], lo[ok], hi[ok])]
        r = np.array(rows, np.float64).reshape(-1, 8)
        return cls(r[:, 0].astype(np.int32), r[:, 1].astype(np.int32), r[:, 2].astype(np.int8),
                   r[:, 3].copy(), r[:, 4:6].copy(), r[:, 6:8].copy(), tree.root_box)

    def of_chunk(self, chunk: int) -> np.ndarray:
        """Indices of the records that border `chunk` (either side)."""
        return np.flatnonzero((self.chunk_a == chunk) | (self.chunk_b == chunk))

    def neighbour(self, chunk: int, axis: int, upward: bool, points) -> np.ndarray:
        """The chunk behind `chunk`'s face on `axis` (its upper face if
        `upward`) at each point of that face; -1 on the root box's boundary.

        Agrees with `ChunkTree.locate(points, ±e_axis)`: as in the tree's tie
        rule, a point on a line where portals meet (a T-junction) belongs to
        the portal above it. So the face is taken half-open: a point on the
        face's own upper edge inside the root box is no point of this face
        (the tree sends it to an edge or corner neighbour) and gives -1 too."""
        p = np.asarray(points, np.float64).reshape(-1, 3)
        mine = self.chunk_a if upward else self.chunk_b
        recs = np.flatnonzero((mine == chunk) & (self.axis == axis))
        other = self.chunk_b if upward else self.chunk_a
        uv = p[:, _OTHER[axis]]
        top = self.root_box[1, _OTHER[axis]]
        inside = (uv[:, None, :] >= self.lo[recs][None]) & (
            (uv[:, None, :] < self.hi[recs][None]) | (uv[:, None, :] == top))
        hit = np.all(inside, axis=2)
        out = np.full(len(p), -1, np.int32)
        rows, cols = np.nonzero(hit)
        out[rows] = other[recs[cols]]
        return out

    def to_wire(self) -> dict:
        return {"count": len(self), **{name: arrays.raw(getattr(self, name), dtype)
                                       for name, dtype, _ in _PORTAL_ARRAYS}}

    @classmethod
    def from_wire(cls, d: dict) -> "Portals":
        n = int(d["count"])
        return cls(*(arrays.from_bytes(d[name], dtype, shape(n), f"portals {name!r}", copy=True)
                     for name, dtype, shape in _PORTAL_ARRAYS))

    def same_as(self, other: "Portals") -> bool:
        return all(np.array_equal(getattr(self, f), getattr(other, f))
                   for f in ("chunk_a", "chunk_b", "axis", "plane", "lo", "hi", "root_box"))


# -- chunk files ---------------------------------------------------------------
def chunk_layout(triangles: int, vertices: int, uv: bool = False, textures: int = 0,
                 texels: int = 0, normals: bool = False) -> tuple[dict, int]:
    """{array name: (offset, nbytes)} and the file size, arrays 64-byte aligned."""
    rows = _rows(vertices, textures, texels)
    out, offset = {}, 0
    for name, dtype, cols in _arrays(uv, textures, normals):
        nbytes = rows.get(name, triangles) * max(cols, 1) * np.dtype(dtype).itemsize
        out[name] = (offset, nbytes)
        offset += -(-nbytes // ALIGN) * ALIGN
    return out, offset


def write_chunk_file(path: str, geometry) -> dict:
    """Write one chunk's arrays; returns its manifest entry (less the file
    name and memory estimate, which the caller adds)."""
    nt, nv = int(geometry.triangles.shape[0]), int(geometry.vertices.shape[0])
    uv, k, n = len(geometry.uv) > 0, len(geometry.tex_ids), len(geometry.texels)
    smooth = len(geometry.normals) > 0
    layout, size = chunk_layout(nt, nv, uv, k, n, smooth)
    h = hashlib.sha256()
    with open(path, "wb") as f:
        for name, dtype, _cols in _arrays(uv, k, smooth):
            offset, nbytes = layout[name]
            pad = b"\0" * (offset - f.tell())
            data = arrays.raw(getattr(geometry, name), dtype)
            assert len(data) == nbytes, name
            for part in (pad, data):
                f.write(part)
                h.update(part)
        pad = b"\0" * (size - f.tell())
        f.write(pad)
        h.update(pad)
    entry = {"triangles": nt, "vertices": nv, "file_bytes": size, "sha256": h.hexdigest(),
             "arrays": {name: list(v) for name, v in layout.items()}}
    if k:
        entry.update(textures=k, texels=n)
    return entry


def partial_path(path: str) -> str:
    """Where the store for `path` is built before being renamed into place."""
    return f"{os.path.abspath(path).rstrip(os.sep)}.partial-{os.getpid()}"


def commit_store(partial: str, path: str, manifest: dict) -> None:
    """Write the manifest last (temp file, fsync, rename), then move the
    finished directory to `path`, replacing an older chunk store there. A
    directory at `path` that is not a chunk store is never deleted."""
    tmp = os.path.join(partial, MANIFEST + ".tmp")
    with open(tmp, "wb") as f:
        f.write(msgpack.packb(manifest))
        f.flush()
        os.fsync(f.fileno())
    os.replace(tmp, os.path.join(partial, MANIFEST))
    _fsync_dir(partial)
    check_target(path)
    old = None
    if os.path.exists(path):
        old = f"{os.path.abspath(path).rstrip(os.sep)}.old-{os.getpid()}"
        os.rename(path, old)
    os.rename(partial, path)
    _fsync_dir(os.path.dirname(os.path.abspath(path)))
    if old:
        shutil.rmtree(old, ignore_errors=True)


def check_target(path: str) -> None:
    """Refuse to replace anything but a chunk store or an empty directory."""
    if os.path.exists(path) and not (os.path.isdir(path) and (
            not os.listdir(path) or _looks_like_store(path))):
        raise StoreError(f"{path}: exists and is not a chunk store; not replacing it")


def is_store(path: str) -> bool:
    """True for a directory with a chunk store manifest (open() validates it)."""
    return os.path.isdir(path) and os.path.exists(os.path.join(path, MANIFEST))


def _looks_like_store(path: str) -> bool:
    names = os.listdir(path)
    return all(n == MANIFEST or (n.startswith("chunk-") and n.endswith(".bin")) for n in names)


def _fsync_dir(path: str) -> None:
    try:
        fd = os.open(path, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)


# -- the store -----------------------------------------------------------------
class ChunkStore:
    """An opened, validated chunk store: what OSPPM and the tracers read.
    Chunk k's geometry is read by `load(k)` from its own file only."""

    def __init__(self, path: str, doc: dict, header: SceneHeader, tree: ChunkTree, portals: Portals):
        self.path, self.manifest = path, doc
        self.header, self.tree, self.portals = header, tree, portals
        self.key = doc["key"]
        self.source_hash = doc["source_hash"]
        self.source_triangles = int(doc["source_triangles"])
        self.budget_bytes = doc["budget_bytes"]
        self.grid = tuple(doc["grid"])
        self.chunks_forced = doc["chunks_forced"]
        self.chunk_count = tree.chunk_count
        entries = doc["chunks"]
        self.chunk_triangles = np.array([e["triangles"] for e in entries], np.int64)
        self.chunk_vertices = np.array([e["vertices"] for e in entries], np.int64)
        self.chunk_memory = np.array([e["memory_bytes"] for e in entries], np.float64)

    @classmethod
    def open(cls, path: str) -> "ChunkStore":
        return cls.from_manifest(path, _read_manifest(path))

    @classmethod
    def from_manifest(cls, path: str, doc: dict, check_files: bool = True) -> "ChunkStore":
        """A store described by manifest `doc` with its chunk files under
        `path`; `check_files=False` for a tracer that fetches its chunk
        files later (each is checked against its SHA-256 when loaded)."""
        where = os.path.join(path, MANIFEST)
        _check_manifest_doc(where, doc)
        try:
            tree = ChunkTree.from_wire(doc["tree"])
        except (KeyError, TypeError, ValueError) as e:
            raise StoreError(f"{where}: field 'tree': {e}") from None
        try:
            header = SceneHeader.from_wire(doc["header"])
        except SceneError as e:
            raise StoreError(f"{where}: field 'header': {e}") from None
        try:
            portals = Portals.from_wire(doc["portals"])
        except (KeyError, TypeError, ValueError) as e:
            raise StoreError(f"{where}: field 'portals': {e}") from None
        if not portals.same_as(Portals.of_tree(tree)):
            raise StoreError(f"{where}: field 'portals' does not match the chunk tree")
        _check_entries(path, doc, tree.chunk_count, check_files)
        return cls(path, doc, header, tree, portals)

    def load(self, k: int, mmap: bool = False):
        """Chunk k's geometry (`ChunkGeometry`), read from its file
        and checked against its SHA-256; `mmap` maps the file instead (no
        checksum: nothing is read until used)."""
        if not 0 <= k < self.chunk_count:
            raise IndexError(f"chunk {k} out of range (store has {self.chunk_count})")
        entry = self.manifest["chunks"][k]
        file = os.path.join(self.path, entry["file"])
        if mmap:
            buf = np.memmap(file, np.uint8, "r")
        else:
            buf = _read_checked(file, entry)
        nt, nv = entry["triangles"], entry["vertices"]
        k = entry.get("textures", 0)
        rows = _rows(nv, k, entry.get("texels", 0))
        out = {}
        for name, dtype, cols in _arrays("uv" in entry["arrays"], k, "normals" in entry["arrays"]):
            offset, nbytes = entry["arrays"][name]
            shape = (rows.get(name, nt), cols) if cols else (rows.get(name, nt),)
            out[name] = arrays.from_bytes(buf[offset:offset + nbytes], dtype, shape, f"{file}: {name!r}")
        return ChunkGeometry(**out)


def _read_manifest(path: str) -> dict:
    where = os.path.join(path, MANIFEST)
    if not os.path.isdir(path):
        raise StoreError(f"{path}: no such chunk store directory")
    if not os.path.exists(where):
        raise StoreError(f"{where}: missing (an interrupted subdivision, or not a chunk store)")
    try:
        with open(where, "rb") as f:
            doc = msgpack.unpackb(f.read())
    except (OSError, ValueError, msgpack.ExtraData) as e:
        raise StoreError(f"{where}: unreadable manifest: {e}") from None
    return doc


def _check_manifest_doc(where: str, doc) -> None:
    if not isinstance(doc, dict) or doc.get("format") != FORMAT:
        raise StoreError(f"{where}: field 'format' is not {FORMAT!r} (a foreign file)")
    if doc.get("version") != FORMAT_VERSION:
        raise StoreError(f"{where}: field 'version' is {doc.get('version')!r}, "
                         f"this program reads version {FORMAT_VERSION}")
    for key in ("key", "tree", "header", "portals", "source_hash", "source_triangles",
                "budget_bytes", "grid", "chunks_forced", "chunks"):
        if key not in doc:
            raise StoreError(f"{where}: field {key!r} missing")


def _check_entries(path: str, doc: dict, chunk_count: int, check_files: bool = True) -> None:
    """Every chunk's entry is consistent and its file has the right size."""
    where = os.path.join(path, MANIFEST)
    entries = doc["chunks"]
    if not isinstance(entries, list) or len(entries) != chunk_count:
        raise StoreError(f"{where}: field 'chunks' does not list {chunk_count} chunks")
    for k, e in enumerate(entries):
        try:
            nt, nv = int(e["triangles"]), int(e["vertices"])
            layout, size = chunk_layout(nt, nv, "uv" in e["arrays"], int(e.get("textures", 0)),
                                        int(e.get("texels", 0)), "normals" in e["arrays"])
            ok = (e["file"] == chunk_file_name(k) and int(e["file_bytes"]) == size
                  and set(e["arrays"]) == set(layout)
                  and all(tuple(e["arrays"][n]) == layout[n] for n in layout)
                  and float(e["memory_bytes"]) >= 0 and isinstance(e["sha256"], str))
        except (KeyError, TypeError, ValueError):
            ok = False
        if not ok:
            raise StoreError(f"{where}: field 'chunks[{k}]' is malformed")
        if not check_files:
            continue
        file = os.path.join(path, e["file"])
        actual = os.path.getsize(file) if os.path.isfile(file) else -1
        if actual != size:
            raise StoreError(f"{file}: {actual} bytes, expected {size} (missing or truncated chunk file)")


def _read_checked(file: str, entry: dict) -> np.ndarray:
    buf = np.empty(int(entry["file_bytes"]), np.uint8)
    try:
        with open(file, "rb") as f:
            got = f.readinto(memoryview(buf))
            extra = f.read(1)
    except OSError as e:
        raise StoreError(f"{file}: cannot read chunk file: {e}") from None
    if got != buf.size or extra:
        raise StoreError(f"{file}: size changed since the store was opened")
    if hashlib.sha256(buf).hexdigest() != entry["sha256"]:
        raise StoreError(f"{file}: checksum mismatch (corrupt chunk file)")
    return buf


# -- reuse -----------------------------------------------------------------------
def store_key(source_hash: str, budget, grid: int, chunks) -> str:
    """Names a store by everything that shapes it: the same key means the
    same chunks, so a cache hit can never be stale."""
    text = f"{FORMAT}/{FORMAT_VERSION}/{source_hash}/{budget}/{grid}/{chunks}"
    return hashlib.sha256(text.encode()).hexdigest()[:24]
