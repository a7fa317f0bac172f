"""The subdivider's memory is set by its settings, not by the scene (issue
17): it holds one block of the source (`--memory`) or one chunk being
written (about 1.5x `--budget`), so a scene several times larger than
that subdivides in it."""
from __future__ import annotations

import os

import numpy as np
import pytest

from dosppm_core.chunks.subdivide import block_for_memory, subdivide
from dosppm_core.scene.generate import generate_building
from dosppm_core.scene.soupfile import open_soup
from harness.subdivide_memory import measure

MiB = 1 << 20


def test_block_size_does_not_change_the_store(tmp_path):
    soup = str(tmp_path / "building")
    generate_building(soup, triangles=60_000, lights=8)
    stores = []
    for name, block in (("small", 5_000), ("large", 1 << 20)):
        report = subdivide(open_soup(soup), str(tmp_path / name), budget_bytes=2 * MiB, block=block)
        stores.append(report.path)
    files = sorted(f for f in os.listdir(stores[0]) if f.endswith(".bin"))
    assert len(files) > 1
    for f in files:
        a, b = (np.fromfile(os.path.join(s, f), np.uint8) for s in stores)
        assert np.array_equal(a, b), f


def test_memory_sets_the_block():
    assert block_for_memory(200 * MiB) == 200 * MiB // 200
    assert block_for_memory(1) == 4096        # never absurdly small


@pytest.mark.slow    # about a minute: 6M triangles generated and subdivided
def test_a_scene_four_times_the_subdividers_memory_subdivides_within_it(tmp_path):
    memory, budget = 16 * MiB, 16 * MiB
    allowed = memory + 2 * budget              # a block, or a chunk being written
    soup = str(tmp_path / "building")
    generate_building(soup, triangles=6_000_000, lights=24)
    # A finer grid than the default: its densest cell must fit the budget.
    doc = measure(soup, str(tmp_path / "store"), budget, memory, grid=262_144)
    assert doc["scene_bytes"] >= 4 * allowed, doc
    assert doc["chunks"] > 1
    # Peak RSS growth while subdividing (VmHWM reset before it starts).
    assert doc["working_bytes"] <= allowed, (
        f"working memory {doc['working_bytes'] / MiB:.0f} MiB for a {doc['scene_bytes'] / MiB:.0f} MiB "
        f"scene; allowed {allowed / MiB:.0f} MiB")
