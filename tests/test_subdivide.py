"""Scene subdivision (§4.1, issue 3) and the chunk store: exact insertion,
budgets, portals, store validation, reuse, the CLI and streaming."""
from __future__ import annotations

import os
from fractions import Fraction

import msgpack
import numpy as np
import pytest

from dosppm_core.chunks.portals import INSERT_MARGIN
from dosppm_core.chunks.store import MANIFEST, ChunkStore, Portals, StoreError, store_key
from dosppm_core.chunks.subdivide import (
    chunk_memory_bytes,
    dedup_geometry,
    open_or_subdivide,
    overlap_matrix,
    source_records,
    subdivide,
    triangle_box_overlap,
)
from dosppm_core.scene import builtin
from dosppm_core.scene.model import SceneError
from dosppm_core.scene.soup import SceneSource
from dosppm_core.scene.soupfile import SoupWriter, open_soup
from tests.helpers.chunks import skewed_tree
from tests.helpers.cli import run_dosppm


# -- a brute-force reference: clip the triangle by the box, in exact rationals --
def clip_overlap(tri, lo, hi, margin=0.0) -> bool:
    """Sutherland-Hodgman against the six closed half-spaces, with Fractions:
    the triangle meets the box iff something of it survives."""
    poly = [tuple(Fraction(float(x)) for x in v) for v in tri]
    m = Fraction(float(margin))
    for a in range(3):
        for bound, sign in ((Fraction(float(lo[a])) - m, 1), (Fraction(float(hi[a])) + m, -1)):
            out = []
            for p, q in zip(poly, poly[1:] + poly[:1]):
                pin, qin = sign * (p[a] - bound) >= 0, sign * (q[a] - bound) >= 0
                if pin:
                    out.append(p)
                if pin != qin:
                    t = (bound - p[a]) / (q[a] - p[a])
                    out.append(tuple(pi + t * (qi - pi) for pi, qi in zip(p, q)))
            poly = out
            if not poly:
                return False
    return True


def _sat(tri, lo, hi, margin=0.0) -> bool:
    return bool(triangle_box_overlap(np.asarray(tri, np.float64), np.asarray(lo, np.float64),
                                     np.asarray(hi, np.float64), float(margin)))


@pytest.mark.parametrize("tri, expect", [
    ([(0.5, 0.5, 0.5), (0.6, 0.5, 0.5), (0.5, 0.6, 0.5)], True),       # fully inside
    ([(2, 2, 2), (3, 2, 2), (2, 3, 2)], False),                          # fully outside
    ([(1, 1, 1), (2, 1, 1), (1, 2, 2)], True),                           # a vertex on the corner
    ([(1, 0, 0), (1, 1, 0), (2, 0, 5)], True),                           # an edge on a box edge
    ([(1, -1, -1), (1, 3, -1), (1, -1, 3)], True),                       # lying in a face plane
    ([(3, 0, 0), (0, 3, 0), (0, 0, 3)], True),                           # plane x+y+z=3 grazes (1,1,1)
    ([(3.5, 0, 0), (0, 3.5, 0), (0, 0, 3.5)], False),                    # bboxes overlap, no touch
    ([(2, -1, 0.5), (-1, 2, 0.5), (2, 2, 0.5)], True),                   # cuts through, no vertex inside
    ([(1.5, 1.5, -1), (1.5, 1.5, 2), (1.5, 1.5, 0)], False),             # degenerate segment beside it
    ([(1, 0.5, -1), (1, 0.5, 2), (1, 0.5, 0)], True),                    # degenerate segment on a face
    ([(1, 1, 1), (1, 1, 1), (1, 1, 1)], True),                           # a point on the corner
])
def test_triangle_box_cases(tri, expect):
    lo, hi = (0, 0, 0), (1, 1, 1)
    assert clip_overlap(tri, lo, hi) == expect
    assert _sat(tri, lo, hi) == expect


def test_triangle_box_matches_clipping_on_random_cases():
    rng = np.random.default_rng(1)
    # Integer coordinates: every touching configuration is hit exactly and the
    # float64 test computes without rounding; a margin of 1/2 keeps it so.
    agree, touching = 0, 0
    for i in range(1500):
        lo = rng.integers(-2, 3, 3).astype(float)
        hi = lo + rng.integers(1, 4, 3)
        tri = rng.integers(-4, 7, (3, 3)).astype(float)
        margin = 0.5 * (i % 2)
        ref = clip_overlap(tri, lo, hi, margin)
        assert _sat(tri, lo, hi, margin) == ref, (tri, lo, hi, margin)
        agree += ref
        touching += ref and not clip_overlap(tri, lo + 1e-3, hi - 1e-3, margin)
    # ... and continuous ones, mostly near the box.
    for _ in range(1500):
        lo = rng.uniform(-1, 0, 3)
        hi = rng.uniform(0.1, 1, 3)
        tri = rng.normal(0, 1.2, (3, 3)) * rng.choice([0.05, 1.0], size=(3, 1))
        tri += rng.normal(0, 1.0, 3)
        margin = rng.choice([0.0, 1e-3])
        ref = clip_overlap(tri, lo, hi, margin)
        assert _sat(tri, lo, hi, margin) == ref, (tri, lo, hi, margin)
        agree += ref
    assert 600 < agree < 2400 and touching > 20


# -- subdividing the built-in glass Cornell box --------------------------------
@pytest.fixture(scope="module")
def glass():
    scene = builtin.make("cornell-glass")
    corners = scene.vertices[scene.triangles]
    return scene, SceneSource(scene), corners


@pytest.fixture(scope="module")
def forced(glass, tmp_path_factory):
    """Stores of the glass box forced into 1, 2, 8 and 27 chunks."""
    _scene, source, _ = glass
    root = tmp_path_factory.mktemp("forced")
    return {c: ChunkStore.open(subdivide(source, str(root / f"c{c}"), chunks=c).path)
            for c in (1, 2, 8, 27)}


def _load_all(store):
    return [store.load(k) for k in range(store.chunk_count)]


@pytest.mark.parametrize("c", [1, 2, 8, 27])
def test_chunks_hold_exactly_the_overlapping_triangles(glass, forced, c):
    scene, source, corners = glass
    store = forced[c]
    assert store.chunk_count == c
    margin = INSERT_MARGIN * scene.diagonal()
    expect = overlap_matrix(corners, store.tree.boxes, margin)
    assert expect.any(axis=1).all(), "every triangle must land in a chunk"
    for k, g in enumerate(_load_all(store)):
        np.testing.assert_array_equal(g.global_id, np.flatnonzero(expect[:, k]))
        np.testing.assert_array_equal(g.vertices[g.triangles], corners[g.global_id])
        np.testing.assert_array_equal(g.tri_material, scene.tri_material[g.global_id])
        assert len(np.unique(g.vertices, axis=0)) == len(g.vertices)   # de-duplicated
        assert store.chunk_memory[k] == chunk_memory_bytes(len(g.triangles), len(g.vertices))
        assert store.chunk_triangles[k] == len(g.triangles)
    if c > 1:
        # Spot-check the exact test where it matters, against clipping:
        # straddling triangles, and bounding-box overlaps it rejected.
        lo, hi = corners.min(axis=1), corners.max(axis=1)
        rng = np.random.default_rng(c)
        boxes = store.tree.boxes
        for k in rng.choice(c, size=min(c, 4), replace=False):
            near = np.all(lo <= boxes[k, 1] + margin, axis=1) & np.all(hi >= boxes[k, 0] - margin, axis=1)
            rejected = np.flatnonzero(near & ~expect[:, k])
            shared = np.flatnonzero(expect[:, k] & (expect.sum(axis=1) > 1))
            for i in np.concatenate([rng.choice(rejected, min(40, len(rejected)), replace=False),
                                     rng.choice(shared, min(40, len(shared)), replace=False)]):
                assert clip_overlap(corners[i], boxes[k, 0], boxes[k, 1], margin) == expect[i, k]


def test_forced_chunks_are_balanced_boxes(forced):
    store = forced[8]
    tri = store.chunk_triangles
    assert tri.max() < 1.3 * tri.min()
    store.tree.validate()
    root = store.tree.root_box
    vol = np.prod(store.tree.boxes[:, 1] - store.tree.boxes[:, 0], axis=1)
    assert np.isclose(vol.sum(), np.prod(root[1] - root[0]))
    # Split planes are grid bin boundaries: the first chunk's faces are too.
    assert store.grid == (32, 32, 32)


# -- budget mode -------------------------------------------------------------
def _node_boxes(tree):
    """(box, parent box) of every leaf of a ChunkTree, by chunk."""
    out = {}
    stack = [(0, tree.root_box.copy(), None)]
    while stack:
        n, box, parent = stack.pop()
        a = int(tree.axis[n])
        if a < 0:
            out[int(tree.child[n, 0])] = (box, parent)
            continue
        lower, upper = box.copy(), box.copy()
        lower[1, a] = upper[0, a] = tree.split[n]
        stack += [(int(tree.child[n, 0]), lower, box), (int(tree.child[n, 1]), upper, box)]
    return out


def _real_memory(corners, box, margin):
    sel = np.flatnonzero(overlap_matrix(corners, box[None], margin)[:, 0])
    g = dedup_geometry(source_records(0, corners[sel], np.zeros(len(sel), np.int32)))
    return chunk_memory_bytes(len(g.triangles), len(g.vertices))


def test_budget_mode_fits_and_splits_no_further_than_needed(glass, forced, tmp_path):
    scene, source, corners = glass
    margin = INSERT_MARGIN * scene.diagonal()
    whole = int(forced[1].chunk_memory[0])
    for factor in (1.0, 3.0):
        s = subdivide(source, str(tmp_path / f"w{factor}"), budget_bytes=int(whole * factor))
        assert s.chunk_count == 1
    counts = []
    for div in (2, 4, 8, 16):
        budget = whole // div
        store = ChunkStore.open(subdivide(source, str(tmp_path / f"b{div}"), budget_bytes=budget).path)
        assert store.chunk_memory.max() <= budget
        assert store.budget_bytes == budget
        counts.append(store.chunk_count)
        if div in (4, 16):
            # Minimal: every chunk's parent would not have fitted.
            for k, (_box, parent) in _node_boxes(store.tree).items():
                assert _real_memory(corners, parent, margin) > budget, k
    ratios = np.array(counts[1:]) / np.array(counts[:-1])
    assert np.all((ratios > 1.4) & (ratios < 3.0)), counts


def test_too_small_budget_is_a_clear_error(glass, tmp_path):
    _scene, source, _ = glass
    out = tmp_path / "tiny"
    with pytest.raises(SceneError, match=r"budget 4\.0 KiB too small for even one grid cell of [\d,]+ "
                                         r"triangles at box") as e:
        subdivide(source, str(out), budget_bytes=4096, grid=4096)
    assert "\n" not in str(e.value)
    assert not out.exists() and not any("partial" in p.name for p in tmp_path.iterdir())


def test_forced_chunks_over_budget_is_an_error(glass, tmp_path):
    with pytest.raises(SceneError, match="over the budget"):
        subdivide(glass[1], str(tmp_path / "s"), budget_bytes=1 << 20, chunks=2)


# -- the store rejects what it cannot trust -----------------------------------
@pytest.fixture
def store_copy(forced, tmp_path):
    import shutil
    dst = tmp_path / "store"
    shutil.copytree(forced[8].path, dst)
    return dst


def _rewrite_manifest(path, change):
    doc = msgpack.unpackb((path / MANIFEST).read_bytes())
    change(doc)
    (path / MANIFEST).write_bytes(msgpack.packb(doc))


def test_store_opens_and_loads_one_chunk(store_copy):
    store = ChunkStore.open(str(store_copy))
    g = store.load(3)
    m = store.load(3, mmap=True)
    for name in ("vertices", "triangles", "tri_material", "global_id"):
        np.testing.assert_array_equal(getattr(g, name), getattr(m, name))
    assert g.vertices.dtype == np.float32 and g.triangles.dtype == np.int32
    assert store.header.name == "cornell-glass" and len(store.portals) > 0
    assert all(off % 64 == 0 for off, _ in store.manifest["chunks"][3]["arrays"].values())


@pytest.mark.parametrize("damage, match", [
    (lambda p: (p / MANIFEST).write_bytes((p / MANIFEST).read_bytes()[:100]), "unreadable manifest|field"),
    (lambda p: (p / MANIFEST).write_bytes(b"\x93garbage"), "manifest"),
    (lambda p: _rewrite_manifest(p, lambda d: d.update(version=2)), "field 'version'"),
    (lambda p: _rewrite_manifest(p, lambda d: d.update(format="other")), "field 'format'"),
    (lambda p: _rewrite_manifest(p, lambda d: d.pop("portals")), "field 'portals'"),
    (lambda p: _rewrite_manifest(p, lambda d: d["tree"].update(split=b"\0" * len(d["tree"]["split"]))),
     "field 'tree'"),
    (lambda p: _rewrite_manifest(p, lambda d: d["header"].pop("camera")), "field 'header'"),
    (lambda p: _rewrite_manifest(p, lambda d: d["chunks"][2].update(triangles=5)), r"chunks\[2\]"),
    (lambda p: os.truncate(p / "chunk-0005.bin", 1000), "chunk-0005.bin.*truncated"),
    (lambda p: os.remove(p / "chunk-0001.bin"), "chunk-0001.bin"),
    (lambda p: os.remove(p / MANIFEST), "missing"),
])
def test_corrupt_store_is_rejected(store_copy, damage, match):
    damage(store_copy)
    with pytest.raises(StoreError, match=match) as e:
        ChunkStore.open(str(store_copy))
    assert "\n" not in str(e.value) and str(store_copy) in str(e.value)


def test_flipped_byte_fails_the_checksum_on_load(store_copy):
    f = store_copy / "chunk-0004.bin"
    data = bytearray(f.read_bytes())
    data[200] ^= 0xFF
    f.write_bytes(bytes(data))
    store = ChunkStore.open(str(store_copy))     # sizes are right: opens
    with pytest.raises(StoreError, match="chunk-0004.bin: checksum"):
        store.load(4)
    store.load(3)


def test_foreign_and_partial_directories_are_rejected(tmp_path, glass):
    foreign = tmp_path / "foreign"
    foreign.mkdir()
    (foreign / "notes.txt").write_text("hello")
    (foreign / MANIFEST).write_bytes(msgpack.packb({"format": "dosppm-soup", "version": 1}))
    with pytest.raises(StoreError, match="format"):
        ChunkStore.open(str(foreign))
    with pytest.raises(StoreError, match="no such"):
        ChunkStore.open(str(tmp_path / "absent"))

    class Interrupted(SceneSource):
        def blocks(self, size=1 << 20):
            yield from super().blocks(20_000)
            raise KeyboardInterrupt
    out = tmp_path / "interrupted"
    with pytest.raises(KeyboardInterrupt):
        subdivide(Interrupted(glass[0]), str(out), chunks=4)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["foreign"]
    # A store whose manifest never got written: chunk files alone.
    out.mkdir()
    (out / "chunk-0000.bin").write_bytes(b"\0" * 64)
    with pytest.raises(StoreError, match="missing"):
        ChunkStore.open(str(out))
    # Never replaces a directory that is not a chunk store.
    with pytest.raises(StoreError, match="not a chunk store"):
        subdivide(glass[1], str(foreign), chunks=2)
    assert (foreign / "notes.txt").exists()


# -- portals --------------------------------------------------------------------
def _trees(forced):
    rng = np.random.default_rng(7)
    box = forced[1].tree.root_box
    return ([forced[c].tree for c in (2, 8, 27)]
            + [skewed_tree(box, rng, n) for n in (5, 12, 30)])


def _on_rect(rng, a, plane, lo, hi, n):
    """n random points on the rectangle, plus its lower corner and points on
    its two lower edges (where T-junctions lie)."""
    u, v = [b for b in range(3) if b != a]
    uv = rng.uniform(lo, hi, (n, 2))
    uv[0] = lo
    uv[1:n // 3, 0] = lo[0]
    uv[n // 3:2 * n // 3, 1] = lo[1]
    p = np.empty((n, 3))
    p[:, a], p[:, u], p[:, v] = plane, uv[:, 0], uv[:, 1]
    return p


def test_portals_resolve_to_the_chunk_locate_finds(forced):
    rng = np.random.default_rng(3)
    t_junctions = 0
    for tree in _trees(forced):
        portals = Portals.of_tree(tree)
        b = tree.boxes
        for i in range(len(portals)):
            ka, kb, a = int(portals.chunk_a[i]), int(portals.chunk_b[i]), int(portals.axis[i])
            assert b[ka, 1, a] == portals.plane[i] == b[kb, 0, a]
            assert np.all(portals.hi[i] > portals.lo[i])
            p = _on_rect(rng, a, portals.plane[i], portals.lo[i], portals.hi[i], 30)
            e = np.zeros((len(p), 3))
            e[:, a] = 1.0
            assert np.all(portals.neighbour(ka, a, True, p) == kb)
            assert np.all(tree.locate(p, e) == kb)
            assert np.all(portals.neighbour(kb, a, False, p) == ka)
            assert np.all(tree.locate(p, -e) == ka)
        t_junctions += _check_faces(tree, portals, rng)
    assert t_junctions > 10


def _check_faces(tree, portals, rng) -> int:
    """Every inner face is tiled by its portals, and random points on it
    agree with locate. Returns the number of faces with several portals."""
    root, several = tree.root_box, 0
    for k, box in enumerate(tree.boxes):
        for a in range(3):
            u, v = [b for b in range(3) if b != a]
            for upward in (False, True):
                plane = box[int(upward), a]
                if plane == root[int(upward), a]:
                    assert len(_face_records(portals, k, a, upward)) == 0
                    continue
                recs = _face_records(portals, k, a, upward)
                area = np.prod(portals.hi[recs] - portals.lo[recs], axis=1).sum()
                assert np.isclose(area, (box[1, u] - box[0, u]) * (box[1, v] - box[0, v]))
                several += len(recs) > 1
                p = _on_rect(rng, a, plane, box[0, (u, v)], box[1, (u, v)], 60)
                d = np.zeros((len(p), 3))
                d[:, a] = 1.0 if upward else -1.0
                assert np.array_equal(portals.neighbour(k, a, upward, p), tree.locate(p, d))
    return several


def _face_records(portals, k, a, upward):
    mine = portals.chunk_a if upward else portals.chunk_b
    return np.flatnonzero((mine == k) & (portals.axis == a))


# -- reuse -----------------------------------------------------------------------
def test_open_or_subdivide_reuses_only_a_matching_store(glass, tmp_path):
    _scene, source, _ = glass
    cache = str(tmp_path / "cache")
    budget = 4 << 20
    a = open_or_subdivide(source, cache, budget=budget)
    stamp = os.stat(os.path.join(a.path, MANIFEST)).st_mtime_ns
    again = open_or_subdivide(source, cache, budget=budget)
    assert again.path == a.path and os.stat(os.path.join(a.path, MANIFEST)).st_mtime_ns == stamp
    b = open_or_subdivide(source, cache, budget=budget // 2)
    assert b.path != a.path and b.budget_bytes == budget // 2 and b.chunk_count > a.chunk_count
    assert store_key(source.content_hash(), budget, 32768, None) == a.key != b.key
    c = open_or_subdivide(source, cache, budget=budget, chunks=8)
    assert c.path not in (a.path, b.path) and c.chunk_count == 8
    os.remove(os.path.join(a.path, "chunk-0000.bin"))     # damaged: made again
    fixed = open_or_subdivide(source, cache, budget=budget)
    assert fixed.path == a.path and fixed.load(0).triangles.shape[0] > 0


# -- the command line ------------------------------------------------------------
def test_cli_subdivide(tmp_path):
    out = tmp_path / "chunks"
    r = run_dosppm("subdivide", "cornell-glass", "--chunks", "8", "--out", str(out))
    assert r.returncode == 0, r.stderr
    assert "8 chunks" in r.stdout and "median" in r.stdout and "duplicated" in r.stdout
    assert "insertion" in r.stdout
    assert ChunkStore.open(str(out)).chunk_count == 8
    bad = run_dosppm("subdivide", "cornell-glass", "--budget", "12 parsecs", "--out", str(tmp_path / "x"))
    assert bad.returncode == 2 and "--budget" in bad.stderr
    assert len(bad.stderr.strip().splitlines()) == 1
    assert not (tmp_path / "x").exists()


# -- streaming from a memory-mapped soup ------------------------------------------
def test_soup_gives_the_same_chunks_as_memory(glass, forced, tmp_path):
    scene, source, corners = glass
    w = SoupWriter(str(tmp_path / "soup"))
    for start in range(0, len(corners), 30_000):
        w.append(corners[start:start + 30_000], scene.tri_material[start:start + 30_000])
    w.close(scene.header())
    soup = open_soup(str(tmp_path / "soup"))
    from dosppm_core.scene.loaders import load_source
    assert type(load_source(str(tmp_path / "soup"))) is type(soup)
    for kw, mem in (({"chunks": 8}, forced[8]), ({"budget_bytes": 1 << 20}, None)):
        if mem is None:
            mem = ChunkStore.open(subdivide(source, str(tmp_path / "mem"), **kw).path)
        # Small blocks: the soup is streamed in 7 pieces.
        disk = ChunkStore.open(subdivide(soup, str(tmp_path / f"disk{len(kw)}{mem.chunk_count}"),
                                         block=16_384, **kw).path)
        assert disk.chunk_count == mem.chunk_count
        np.testing.assert_array_equal(disk.tree.boxes, mem.tree.boxes)
        for k in range(mem.chunk_count):
            a, b = disk.load(k), mem.load(k)
            for name in ("vertices", "triangles", "tri_material", "global_id"):
                np.testing.assert_array_equal(getattr(a, name), getattr(b, name))
