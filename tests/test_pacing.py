"""Work chosen to hide chunk loads (issue 17): the pacing rule, a tracer's
queue target, the server's queue allowance that follows it, and OSPPM's photons per
iteration growing only when chunks do not all fit."""
from __future__ import annotations

import numpy as np
import pytest

from dosppm_core.chunks import pacing
from dosppm_core.modes.osppm import OutOfCoreRenderer
from dosppm_core.settings import LIGHT_CACHE_BYTES, RenderSettings
from dosppm_core.trace import LEARN
from services.server.emission import EMIT_PHOTONS_PER_TICK
from services.tracer.state import TracerState
from tests.helpers.chunks import MemoryChunks, root_box, uniform_tree
from tests.helpers.scenes import small_scene
from tests.test_scheduler import _register, _results, new_state


@pytest.fixture(scope="module")
def four_chunks():
    scene = small_scene("cornell-box", 32)
    return MemoryChunks(scene, uniform_tree(root_box(scene), (2, 2, 1)))


def test_work_grows_until_loads_are_a_tenth_of_a_sweep():
    # 1 s of loads a sweep, 100k rays traced in 1 s: 900k rays trace for
    # 9 s, so the loads are 1 s of 10.
    assert pacing.work_to_hide_loads(1.0, 1.0, 100_000) == pytest.approx(900_000)
    assert pacing.work_to_hide_loads(0.5, 1.0, 100_000) == pytest.approx(450_000)
    assert pacing.work_to_hide_loads(0.0, 1.0, 100_000) == 0.0      # nothing loaded: nothing to hide
    assert pacing.work_to_hide_loads(1.0, 0.0, 0) == 0.0


def test_growth_is_bounded_capped_and_never_a_shrink():
    assert pacing.grown(1000, 10_000, 1_000_000) == 4000
    assert pacing.grown(1000, 10_000, 1_000_000, first=True) == 10_000     # the first measurement may jump
    assert pacing.grown(1000, 1500, 1_000_000) == 1500
    assert pacing.grown(1000, 10, 1_000_000) == 1000
    assert pacing.grown(1000, 10_000, 1200) == 1200
    assert pacing.queue_cap_rays(pacing.RAY_BYTES * 1000) == 1000
    assert pacing.queue_cap_rays(None) == pacing.default_queue_memory() // pacing.RAY_BYTES


def _cgroup(tmp_path, lines: str, limits: dict[str, str]):
    proc = tmp_path / "proc"
    proc.mkdir(parents=True)
    (proc / "cgroup").write_text(lines)
    for path, text in limits.items():
        f = tmp_path / "cg" / path
        f.parent.mkdir(parents=True, exist_ok=True)
        f.write_text(text + "\n")
    return pacing.cgroup_memory_limit(str(proc), str(tmp_path / "cg"))


def test_the_cgroup_limit_is_the_tightest_of_the_process_group_and_its_ancestors(tmp_path):
    v2 = "0::/kubepods/pod1/box\n"
    assert _cgroup(tmp_path / "a", v2, {"kubepods/memory.max": "max", "kubepods/pod1/memory.max": "419430400",
                                         "kubepods/pod1/box/memory.max": "max"}) == 400 << 20
    # No file says a number: no limit, and the machine's memory counts.
    assert _cgroup(tmp_path / "b", v2, {"memory.max": "max", "kubepods/pod1/box/memory.max": "max"}) is None
    # cgroup v1: the memory controller's file; its "unlimited" is a page-rounded 2^63.
    v1 = "4:memory:/docker/abc\n3:cpu:/\n"
    assert _cgroup(tmp_path / "c", v1, {"memory/docker/abc/memory.limit_in_bytes": "268435456"}) == 256 << 20
    assert _cgroup(tmp_path / "d", v1, {"memory/docker/abc/memory.limit_in_bytes": "9223372036854771712"}) is None
    assert pacing.cgroup_memory_limit(str(tmp_path / "absent"), str(tmp_path)) is None


def test_the_default_queue_memory_follows_the_machine_within_its_bounds():
    GiB = 1 << 30
    assert pacing.default_queue_memory(8 * GiB) == 512 << 20
    assert pacing.default_queue_memory(24 * GiB) == pacing.QUEUE_MEMORY_MAX       # a workstation: the cap
    assert pacing.default_queue_memory(400 << 20) == pacing.QUEUE_MEMORY_MIN      # a small container: the floor
    assert pacing.QUEUE_MEMORY_MIN <= pacing.default_queue_memory() <= pacing.QUEUE_MEMORY_MAX


def test_the_default_chunk_memory_is_a_share_of_the_machine_less_what_a_process_holds():
    GiB, MiB = 1 << 30, 1 << 20
    base, q = pacing.PROCESS_BASE_BYTES, pacing.default_queue_memory
    # A local render on a 24 GiB workstation: a server and two tracers.
    assert pacing.default_chunk_memory(3, 24 * GiB) == int(8 * GiB - base - 1.5 * q(24 * GiB))
    # One worker alone in a 400 MiB container: what is left for chunks.
    assert pacing.default_chunk_memory(1, 400 * MiB) == int(400 * MiB - base - 1.5 * 32 * MiB)
    assert pacing.default_chunk_memory(4, 400 * MiB) == 0          # nothing left: never negative
    assert pacing.default_chunk_memory(1) > pacing.default_chunk_memory(3)


def test_a_tracer_on_a_machine_smaller_than_its_chunks_keeps_a_share_of_it(four_chunks, monkeypatch):
    """Its chunks' memory when given none: what the machine (or cgroup)
    leaves it, less its light cache, not all its chunks; at least one
    chunk, so it can render."""
    largest = max(four_chunks.chunk_memory)
    room = pacing.PROCESS_BASE_BYTES + 1.5 * pacing.QUEUE_MEMORY_MIN
    monkeypatch.setattr(pacing, "machine_memory_bytes", lambda: int(room + 2.5 * largest))
    t = _tracer(four_chunks, None)
    try:
        cache = min(LIGHT_CACHE_BYTES, 1.5 * largest)       # the light cache counts in it, up to one chunk less
        assert t.lights[LEARN][0].nbytes > 0
        assert t.cache.memory == pytest.approx(2.5 * largest - cache, abs=2) and not t.all_fit()
    finally:
        t.close()
    monkeypatch.setattr(pacing, "machine_memory_bytes", lambda: int(room))
    t = _tracer(four_chunks, None)
    try:
        assert t.cache.memory == largest
    finally:
        t.close()


class _Clock:
    def __init__(self):
        self.t = 0.0

    def __call__(self) -> float:
        return self.t


def _tracer(provider, memory, queue_memory=None, clock=None):
    t = TracerState("inproc://t", provider, 10, memory_bytes=memory, queue_memory_bytes=queue_memory,
                    clock=clock or _Clock())
    t.set_peers(1, [["inproc://t"]] * provider.tree.chunk_count)
    return t


def _measured(t, loads, load_s, busy_s, rays):
    cc = t.cache.counters
    cc.loads, cc.load_seconds, cc.wait_seconds = loads, load_s, 0.0
    t.counters["busy_s"], t.counters["rays_traced"] = busy_s, rays
    t._pace()
    return t.queue_target()


def test_a_tracer_whose_chunks_do_not_fit_asks_for_a_sweep_of_dwells_within_its_latency(four_chunks):
    """Issue 31: each chunk visit dwells a load's cost over LOAD_SHARE, so
    the queue asks for a sweep of dwells at the tracing rate, but no more
    than the tracer gets through in pacing.LATENCY_S, loads included."""
    clock = _Clock()
    t = _tracer(four_chunks, 1.5 * max(four_chunks.chunk_memory), queue_memory=256 << 20, clock=clock)
    try:
        assert t.queue_target() == 0
        clock.t = 1.0                      # the first sweep: cold loads, nothing to go by
        assert _measured(t, 4, 1.0, 1.0, 100_000) == 0
        dwell = pacing.dwell_s(0.25)
        assert t.schedule.dwell_s == pytest.approx(dwell) and dwell == pytest.approx(2.25)
        # Tracing at 550k rays/s a sweep of dwells is 4 * 2.25 s of it;
        # 1M rays got through in the last second: 3 s of those is less.
        clock.t = 2.0
        assert _measured(t, 8, 2.0, 2.0, 1_100_000) == pytest.approx(1_000_000 * pacing.LATENCY_S, rel=1e-6)
        assert _measured(t, 9, 2.25, 2.0, 9_000_000) == pytest.approx(3_000_000, rel=1e-6)   # not a sweep since
        # Tracing slowly (100k rays a second of tracing): the sweep of
        # dwells, 900k rays, is less than the 1.2M got through in 3 s.
        clock.t = 3.0
        assert _measured(t, 12, 3.0, 15.0, 1_500_000) == pytest.approx(4 * dwell * 100_000, rel=1e-6)
        # A tracer that got through little still gets the server's first queue allowance.
        clock.t = 103.0
        assert _measured(t, 16, 4.0, 16.0, 1_600_000) == pacing.FIRST_QUEUE_RAYS
        # Bounded by --queue-memory.
        small = _tracer(four_chunks, 1.5 * max(four_chunks.chunk_memory), queue_memory=pacing.RAY_BYTES * 600_000,
                        clock=clock)
        _measured(small, 4, 1.0, 1.0, 50_000)
        clock.t = 104.0
        assert _measured(small, 8, 2.0, 2.0, 2_000_000) == 600_000
        small.close()
    finally:
        t.close()


def test_a_tracer_holding_all_its_chunks_leaves_the_queue_allowance_to_the_server(four_chunks):
    t = _tracer(four_chunks, None)
    try:
        assert _measured(t, 4, 1.0, 1.0, 1_000_000) == 0
    finally:
        t.close()


def test_the_server_sends_what_a_tracer_asks_for_a_tick_at_a_time():
    state = new_state((1, 1, 1), photons_per_job=1024)
    _register(state, "a")
    state.cull_box = np.array([[-1e9] * 3, [1e9] * 3])
    state.eye_completed = 1

    def photons_sent(now):
        return sum(int(o.fields["counts"].sum()) for o in state.tick(now) if o.type == "photon_job")

    assert photons_sent(0.0) <= 4096 + 1024            # the server's queue allowance
    asked = 3 * EMIT_PHOTONS_PER_TICK
    msg = _results([], [])
    msg.queue_target = asked
    state.on_message("a", msg, 0.05)
    assert state.allowance_of(state.tracers["a"]) == asked
    assert state.photon_jobs_in_flight <= state.min_photon_jobs + 5
    ticks = [photons_sent(0.1 * i) for i in range(1, 6)]
    assert max(ticks) <= EMIT_PHOTONS_PER_TICK             # the loop stays responsive
    # Then it stops at the new allowance, overshooting by less than a job.
    assert 0.95 * asked <= sum(ticks) <= asked + 1024
    assert state.photon_jobs_in_flight >= asked // 1024
    # The time limit counts the queue's drain: its rays at the tracer's rate.
    t = state.tracers["a"]
    t.status = {"busy_s": 10.0, "rays_traced": 1_000_000}
    assert t.load_estimate > 0 and state.drain_estimate_s() == pytest.approx(t.load_estimate * 1e-5)



def _queue_filled(asked: int):
    """A server whose one tracer asked for `asked` queued rays, sent them."""
    state = new_state((1, 1, 1), photons_per_job=1024)
    _register(state, "a")
    state.cull_box = np.array([[-1e9] * 3, [1e9] * 3])
    state.eye_completed = 1
    msg = _results([], [])
    msg.queue_target = asked
    state.on_message("a", msg, 0.0)
    for i in range(1, 8):
        state.tick(0.1 * i)
    return state


def _sent_after_report(state, queued: int, t0: float) -> int:
    msg = _results([], [])
    msg.queue_target, msg.queued = state.tracers["a"].queue_target, queued
    state.on_message("a", msg, t0)
    return sum(int(o.fields["counts"].sum()) for i in range(1, 8) for o in state.tick(t0 + 0.1 * i)
               if o.type == "photon_job")


def test_jobs_whose_rays_left_the_queue_do_not_hold_the_queue_short():
    """Out of core a photon job stays in flight until its last path ends,
    sweeps after most of its rays were traced. The tracer reports its
    queue empty, no job complete: the server refills the queue. The
    control, its queue still full, gets nothing more."""
    asked = 2 * EMIT_PHOTONS_PER_TICK
    drained, full = _queue_filled(asked), _queue_filled(asked)
    jobs = drained.photon_jobs_in_flight
    assert jobs >= 0.95 * asked // 1024
    assert _sent_after_report(drained, 0, 1.0) >= 0.9 * asked
    assert drained.photon_jobs_in_flight >= jobs + 0.9 * asked // 1024
    assert _sent_after_report(full, asked, 1.0) <= 1024

def _osppm(provider, memory, **kw):
    settings = RenderSettings(seed=3, photons_per_job=1024, **kw)
    # Queued rays for 400k photons: paced runs start at 50k photons per
    # iteration (a quarter of the 200k the limit allows them).
    return OutOfCoreRenderer(provider, settings, memory_bytes=memory, queue_memory_bytes=pacing.RAY_BYTES * 400_000)


def test_osppm_grows_photons_per_iteration_only_when_chunks_do_not_fit(four_chunks):
    tight = 1.5 * max(four_chunks.chunk_memory)
    o = _osppm(four_chunks, tight)
    try:
        assert o.paced and o.max_photons_per_iteration == 200_000
        assert o.settings.photons_per_iteration == 50_000
        o.run_iteration()                                 # measured loads: it may grow, never shrink
        assert o.progress().photons_emitted >= 50_000 and o.settings.photons_per_iteration >= 50_000
        o.settings.photons_per_iteration, o.iteration = 10_000, 2     # a later iteration's measurement
        o._pace(load_s=1.0, trace_s=0.1)                  # loads dominate: at most 4x after the first
        assert o.settings.photons_per_iteration == 4 * 10_000
        o._pace(load_s=0.001, trace_s=10.0)               # hidden already: never shrink
        assert o.settings.photons_per_iteration == 4 * 10_000
        for _ in range(10):
            o._pace(load_s=1.0, trace_s=0.1)
        assert o.settings.photons_per_iteration == 200_000
    finally:
        o.close()
    for memory, kw in ((None, {}), (tight, {"photons_per_iteration": 20_000})):
        o = _osppm(four_chunks, memory, **kw)
        try:
            assert not o.paced
            before = o.settings.photons_per_iteration
            assert before == (20_000 if kw else 10_000)   # 1.5 per pixel, at least 10k; or as given
            o._pace(load_s=1.0, trace_s=0.1)
            assert o.settings.photons_per_iteration == before
        finally:
            o.close()


def test_a_smaller_queue_memory_makes_osppm_batches_smaller(four_chunks):
    """OSPPM's --queue-memory: half for the queued rays, a quarter for the
    deposits waiting for an update, an eighth for a tracing step's rays. At
    the default the paper's 1M batch fits; at 64 MiB a batch is 16 MiB of
    deposits and a step 131k rays."""
    for queue_memory, batch in ((None, 1_000_000), (64 << 20, (16 << 20) // pacing.DEPOSIT_BYTES)):
        o = OutOfCoreRenderer(four_chunks, RenderSettings(seed=1), queue_memory_bytes=queue_memory)
        try:
            assert o.settings.photon_batch == batch
            assert o.trace_step_rays == min(262_144, pacing.queue_cap_rays(queue_memory) // 8)
            assert o.max_photons_per_iteration == pacing.queue_cap_rays(queue_memory) // 2
        finally:
            o.close()


def test_paced_osppm_emits_only_what_fits_beside_the_rays_carried_over(four_chunks):
    """A pipelined sweep carries rays into the next iteration; a paced
    iteration emits only as many photons as fit beside them, so what is
    queued stays within its half of --queue-memory (a job's worth over at
    most). Control: with the rule off, carried rays plus a full iteration
    go over."""
    queued = {}
    for rule in (True, False):
        o = _osppm(four_chunks, 1.5 * max(four_chunks.chunk_memory))
        if not rule:
            o._photons_to_emit = lambda: o.settings.photons_per_iteration
        emit, after = o._emit_photons, []

        def spy():
            emit()
            after.append(o.rays_queued)
        o._emit_photons = spy
        try:
            o.run_iteration()
            o.settings.photons_per_iteration = o.max_photons_per_iteration      # paced to its cap
            for _ in range(3):
                o.run_iteration()
        finally:
            o.close()
        queued[rule] = max(after[1:])
    assert queued[True] <= o.max_photons_per_iteration + o.settings.photons_per_job, queued
    assert queued[False] > o.max_photons_per_iteration + o.settings.photons_per_job, queued
