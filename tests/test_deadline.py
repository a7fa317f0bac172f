"""`--time T` is a deadline in every mode (issue 29): the process exits with
its image written within max(2 s, 5% of T) after T, counted from the
render's clock (its start is in OUT.json for the service, in the progress
log for one process). Out of core, on a building cut into chunks with
little memory for each, the service's work in flight at the deadline is
applied or discarded whole, job by job, and counted; its ledger still
re-traces to its totals (exactly once), and N_e is the photons applied."""
from __future__ import annotations

import json
import time

import numpy as np
import pytest

from dosppm_core.chunks.store import ChunkStore
from dosppm_core.film import read_exr
from dosppm_core.modes.deadline import grace_s
from dosppm_core.scene.generate import generate_building
from services import ledger
from tests.helpers.cli import run_dosppm

pytestmark = pytest.mark.slow

T = 8.0


@pytest.fixture(scope="module")
def store(tmp_path_factory):
    """A 300k-triangle building in chunks of 8 MiB at most (8 or more)."""
    tmp = tmp_path_factory.mktemp("deadline")
    generate_building(str(tmp / "soup"), triangles=300_000, lights=40, width=96, height=72)
    done = run_dosppm("subdivide", str(tmp / "soup"), "--budget", "8MiB", "--out", str(tmp / "store"))
    assert done.returncode == 0, done.stderr
    s = ChunkStore.open(str(tmp / "store"))
    assert s.chunk_count >= 8, s.chunk_count
    return s


def _started(log) -> float:
    with open(log, encoding="utf-8") as f:
        return json.loads(f.readline())["started_unix"]


def _check(out, started_unix: float, ended_unix: float) -> float:
    late = ended_unix - (started_unix + T)
    print(f"\n{out.name}: exited {late:+.2f} s after the {T:g} s deadline (grace {grace_s(T):g} s)")
    assert late <= grace_s(T), late
    img, _ = read_exr(str(out))
    assert np.isfinite(img).all() and img.mean() > 0
    return late


def test_the_service_out_of_core_keeps_its_deadline_and_its_ledger(store, tmp_path):
    # Two tracers, each with room for two chunks: loads all through the render.
    memory = str(int(2.2 * store.chunk_memory.max()))
    out = tmp_path / "service.exr"
    done = run_dosppm("render", store.path, "--tracers", "2", "--memory", memory, "--time", str(T),
                      "--out", str(out), "--http", "off", "--ledger", str(tmp_path / "r.ledger"), "--quiet")
    ended = time.time()
    assert done.returncode == 0, done.stderr[-3000:]
    summary = json.loads(out.with_suffix(".json").read_text())
    _check(out, summary["started_unix"], ended)
    c = summary["counters"]
    # Every photon emitted is committed, left out whole at the deadline, or
    # discarded with a lost tracer and re-emitted (none here).
    assert c["photons_emitted"] == c["photons_committed"] + c["photons_abandoned"] + c["photons_discarded"]
    assert summary["photons_in_image"] == c["photons_committed"] > 0
    problems = ledger.check(ChunkStore.open(store.path), ledger.read(str(tmp_path / "r.ledger")))
    assert not problems, problems


@pytest.mark.parametrize("mode", ["osppm", "sppm"])
def test_one_process_keeps_its_deadline(store, tmp_path, mode):
    """OSPPM on the building with room for two chunks; SPPM on the built-in
    glass knot (it renders a whole scene in memory)."""
    out, log = tmp_path / f"{mode}.exr", tmp_path / f"{mode}.jsonl"
    scene = [store.path, "--memory", str(int(2.2 * store.chunk_memory.max()))] if mode == "osppm" \
        else ["cornell-glass"]
    done = run_dosppm("render", *scene, "--mode", mode, "--time", str(T), "--out", str(out),
                      "--log", str(log), "--quiet")
    ended = time.time()
    assert done.returncode == 0, done.stderr[-3000:]
    _check(out, _started(log), ended)
