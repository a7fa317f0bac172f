"""A tracer's bounce kernels keep to its --threads, as its Embree tracing
does. numba's parallel kernels otherwise take every core: beside another
tracer and the server, a kernel's second OpenMP thread waits for a core
while the tracing thread sleeps at the barrier (measured on the 5M-triangle
building, 8 chunks, 2 tracers, side by side: every chunk resident, 30 s,
751-805k photons/s before, 817-841k after; out of core, 60 s, medians of
3, 878k before, 930k after)."""
from __future__ import annotations

import os
import threading

import numba
import pytest

from dosppm_core.chunks.store import ChunkStore
from dosppm_core.chunks.subdivide import subdivide
from dosppm_core.scene.soup import SceneSource
from dosppm_core.settings import RenderSettings
from services.server.node import ServerProcess
from services.server.options import Limits, ServerOptions
from services.tracer.node import TracerOptions, TracerProcess
from services.tracer.state import TracerState
from tests.helpers.scenes import small_scene


class _Recording(TracerState):
    seen: set = set()

    def step(self):
        _Recording.seen.add(numba.get_num_threads())
        return super().step()


@pytest.mark.skipif(numba.config.NUMBA_NUM_THREADS < 2, reason="numba found one core: nothing to keep to")
def test_a_one_thread_tracer_runs_its_kernels_on_one_thread(tmp_path, monkeypatch):
    subdivide(SceneSource(small_scene("cornell-box", 16)), str(tmp_path / "s"), chunks=2)
    store = ChunkStore.open(str(tmp_path / "s"))
    server = ServerProcess(store, RenderSettings(threads=2, photons_per_job=512), ServerOptions(
        bind="tcp://127.0.0.1:*", http=None, out=str(tmp_path / "out.exr"), limits=Limits(photons=20_000),
        min_photon_jobs=8))
    ran = threading.Thread(target=server.run, daemon=True)
    ran.start()
    monkeypatch.setattr(TracerProcess, "state_class", _Recording)
    _Recording.seen = set()
    tracer = TracerProcess(TracerOptions(server.endpoint, store=store.path, threads=1, tracer_id="one"))
    assert numba.get_num_threads() == numba.config.NUMBA_NUM_THREADS   # this thread: the default
    serving = threading.Thread(target=tracer.run, daemon=True)
    serving.start()
    ran.join(120)
    serving.join(30)
    assert not ran.is_alive() and not serving.is_alive()
    assert _Recording.seen == {1}
    assert os.path.exists(tmp_path / "out.exr")
