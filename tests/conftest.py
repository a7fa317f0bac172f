"""Fixtures and skips shared by the test files.

Tiers (markers registered in pyproject.toml): `slow` (long convergence
renders, multi-process clusters), `netns` (hosts as network namespaces:
root and iproute2), `docker`, `browser` (headless Chromium) and
`reference` (Mitsuba 3). The fast tier is

    python -m pytest -m "not slow and not netns and not docker and not browser"

and plain `python -m pytest` runs every tier. Plain functions the tests
share (paths, the `dosppm` child process, free ports, small scenes, chunk
helpers) are in tests/helpers/.
"""
from __future__ import annotations

import importlib.util

import pytest

from dosppm_core.chunks.store import ChunkStore
from dosppm_core.chunks.subdivide import subdivide
from dosppm_core.scene.soup import SceneSource

MITSUBA_MISSING = importlib.util.find_spec("mitsuba") is None


def pytest_runtest_setup(item):
    """A test marked `reference` needs Mitsuba 3: skipped where the
    [reference] extra is not installed, instead of failing on the import."""
    if MITSUBA_MISSING and item.get_closest_marker("reference") is not None:
        pytest.skip("needs Mitsuba 3 (pip install -e '.[reference]')")


@pytest.fixture
def mi():
    """Mitsuba 3 in its scalar_rgb variant (the one our references use),
    set again for each test since another may have switched it; skips the
    test without Mitsuba."""
    mitsuba = pytest.importorskip("mitsuba")
    mitsuba.set_variant("scalar_rgb")
    return mitsuba


@pytest.fixture
def chunk_store(tmp_path):
    """chunk_store(scene, chunks) -> a ChunkStore of `scene` subdivided by
    the real subdivider (exact triangle-box insertion) into `chunks`
    chunks, in a folder of its own under the test's tmp_path."""
    made = []

    def make(scene, chunks: int) -> ChunkStore:
        path = tmp_path / f"store-{len(made)}"
        subdivide(SceneSource(scene), str(path), chunks=chunks)
        made.append(path)
        return ChunkStore.open(str(path))
    return make
