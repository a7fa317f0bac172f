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

import collections
import importlib.util
import os

import pytest

from dosppm_core.chunks.store import ChunkStore
from dosppm_core.chunks.subdivide import subdivide
from dosppm_core.scene.soup import SceneSource
from tests.helpers import figures

MITSUBA_MISSING = importlib.util.find_spec("mitsuba") is None
MARKERS = ("slow", "netns", "docker", "browser", "reference")
# Skips CI may never take quietly: with DOSPPM_REQUIRE_ALL=1 a test that
# would skip for want of one of these fails instead. pbrt-v4 is not here:
# CI never builds it (its tests skip without it, by design).
REQUIRED = ("chromium", "`ip`", "iproute2", "iptables", "docker", "mitsuba", "shared folder",
            "../shared", "namespace", "matplotlib", "one core")
# Tiers that skip only for want of their tool: under DOSPPM_REQUIRE_ALL
# any skip of one of their tests fails, whatever its reason says, so a
# reworded reason cannot slip past the words above. Not `reference`: the
# pbrt-v4 peer tests are in it and skip by design.
REQUIRED_TIERS = ("netns", "docker", "browser")
_TALLY: dict = collections.defaultdict(collections.Counter)
_SKIPS: collections.Counter = collections.Counter()


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_makereport(item, call):
    """Tally outcomes per marker (printed at the end), and under
    DOSPPM_REQUIRE_ALL turn a skip for a missing tool, or any skip in a
    tool's tier, into a failure."""
    rep = (yield).get_result()
    if rep.skipped and not hasattr(rep, "wasxfail"):      # an expected failure is no skip
        reason = str(rep.longrepr[2] if isinstance(rep.longrepr, tuple) else rep.longrepr)
        _SKIPS[reason] += 1
        required = any(w in reason.lower() for w in REQUIRED) or \
            any(item.get_closest_marker(t) for t in REQUIRED_TIERS)
        if os.environ.get("DOSPPM_REQUIRE_ALL") == "1" and required:
            rep.outcome, rep.longrepr = "failed", f"DOSPPM_REQUIRE_ALL=1, and this test would skip: {reason}"
    # Tallied after that, so the tier counts say "failed" as pytest does.
    if rep.when == "call" or rep.outcome != "passed":
        tiers = [m for m in MARKERS if item.get_closest_marker(m)] or ["fast"]
        outcome = "error" if rep.failed and rep.when != "call" else rep.outcome
        for tier in tiers:
            _TALLY[tier][outcome] += 1


@pytest.hookimpl(hookwrapper=True)
def pytest_make_collect_report(collector):
    """A module that skips as it is imported (`pytest.importorskip`) skips
    every test in it: under DOSPPM_REQUIRE_ALL, for a missing tool, that
    fails too."""
    rep = (yield).get_result()
    if rep.skipped and os.environ.get("DOSPPM_REQUIRE_ALL") == "1":
        reason = str(rep.longrepr[2] if isinstance(rep.longrepr, tuple) else rep.longrepr)
        if any(w in reason.lower() for w in REQUIRED):
            rep.outcome, rep.longrepr = "failed", f"DOSPPM_REQUIRE_ALL=1, and {rep.nodeid} would skip: {reason}"


def pytest_terminal_summary(terminalreporter):
    """What ran, per tier, and why anything skipped: CI says what it ran."""
    written = figures.write_if_asked()
    if written:
        terminalreporter.write_line(f"reliability figures merged into {written}")
    if not _TALLY:
        return
    tr = terminalreporter
    tr.section("tests per tier")
    for tier in ("fast", *MARKERS):
        if tier in _TALLY:
            tr.write_line(f"{tier:10s} " + ", ".join(f"{n} {k}" for k, n in sorted(_TALLY[tier].items())))
    for reason, n in _SKIPS.most_common():
        tr.write_line(f"skipped {n}: {reason}")


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
