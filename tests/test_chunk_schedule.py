"""The chunk scheduler that OSPPM and every tracer share (issue 31): eye
work goes first within a chunk and, by weighted waiting time, between
chunks; photon work dwells on a chunk when not all fit; photons go oldest
job first; batches coalesce up to the step size; the counts stay exact."""
from __future__ import annotations

from dosppm_core.chunks.schedule import EYE, EYE_PRIORITY, PHOTON, SHADOW, ChunkScheduler


class Rays:
    """A package of `n` rays, named for the asserts."""

    def __init__(self, name: str, n: int = 10):
        self.name, self.n = name, n

    def __len__(self) -> int:
        return self.n


class Clock:
    def __init__(self):
        self.t = 0.0

    def __call__(self) -> float:
        return self.t


def _scheduler(chunks: int, step_rays: int = 10, dwell_s: float = 1.0):
    clock = Clock()
    return ChunkScheduler(chunks, step_rays, dwell_s=dwell_s, clock=clock), clock


def _names(taken) -> list[str]:
    return [x.name for x in taken.items]


def test_a_chunk_that_eye_rays_wait_for_is_picked_before_photon_chunks():
    s, clock = _scheduler(4, step_rays=100)
    for k in (0, 1, 3):
        s.push(k, PHOTON, Rays(f"p{k}"))
    s.push(2, EYE, Rays("e2"), eye_iteration=0)
    clock.t = 1.0
    assert s.pick(all_fit=False) == 2
    assert s.take(2).kind == EYE
    clock.t = 2.0                    # eye work gone, its dwell over: photons, round robin after it
    assert s.pick(all_fit=False) == 3


def test_photons_that_waited_long_enough_go_before_fresh_eye_work():
    """Strict eye priority between chunks starved photons (no photon job
    completed in 20 s out of core): a photon package's wait catches up."""
    def first(eye_wait: float) -> int:
        s, clock = _scheduler(2, dwell_s=100.0)
        s.push(0, PHOTON, Rays("p0"))
        clock.t = 2 * EYE_PRIORITY - eye_wait
        s.push(1, EYE, Rays("e1"), eye_iteration=0)
        clock.t = 2 * EYE_PRIORITY             # the photons have waited 2 * EYE_PRIORITY
        return s.pick(False)
    assert first(eye_wait=1.0) == 0            # 1 s x EYE_PRIORITY is less
    assert first(eye_wait=2.5) == 1


def test_the_active_chunk_keeps_its_eye_work_then_shadows_go_next():
    s, clock = _scheduler(3, dwell_s=10.0)
    s.push(0, PHOTON, Rays("p0"))
    s.push(1, EYE, Rays("e1a"), eye_iteration=0)
    s.push(1, EYE, Rays("e1b"), eye_iteration=0)
    s.push(2, SHADOW, Rays("s2"), eye_iteration=0)
    clock.t = 1.0
    assert s.pick(False) == 1 and _names(s.take(1)) == ["e1a"]
    clock.t = 2.0
    assert s.pick(False) == 1 and _names(s.take(1)) == ["e1b"]
    clock.t = 20.0                    # chunk 1's dwell over
    assert s.pick(False) == 2 and s.take(2).kind == SHADOW
    assert s.pick(False) == 0 and s.take(0).kind == PHOTON
    assert s.pick(False) is None and not s.has_work()


def test_photons_dwell_on_the_active_chunk_only_while_not_all_fit():
    def visits(all_fit: bool) -> list[int]:
        s, clock = _scheduler(2, dwell_s=3.0)
        for k in (0, 1):
            for i in range(8):
                s.push(k, PHOTON, Rays(f"p{k}{i}"))
        seen = []
        for t in range(8):                   # a step a second
            clock.t = float(t)
            k = s.pick(all_fit)
            s.take(k)
            seen.append(k)
        return seen
    assert visits(all_fit=False) == [0, 0, 0, 1, 1, 1, 0, 0]     # 3 s on each
    assert visits(all_fit=True) == [0, 1, 0, 1, 0, 1, 0, 1]


def test_eye_work_elsewhere_waits_for_the_dwell_then_goes_first():
    """No load is cut short: out of core each switch costs one."""
    s, clock = _scheduler(3, dwell_s=2.0)
    for i in range(5):
        s.push(0, PHOTON, Rays(f"p{i}"))
    s.push(2, PHOTON, Rays("old"))
    assert s.pick(False) == 0
    s.take(0)
    s.push(1, EYE, Rays("e"), eye_iteration=0)
    clock.t = 1.0
    assert s.pick(False) == 0
    s.take(0)
    clock.t = 2.0
    assert s.pick(False) == 1          # waited 1 s, x EYE_PRIORITY: before chunk 2's 2 s


def test_the_prefetch_is_the_chunk_picked_next():
    s, clock = _scheduler(5)
    s.push(1, PHOTON, Rays("p1"))
    s.push(2, PHOTON, Rays("p2"))
    s.push(4, EYE, Rays("e4"), eye_iteration=0)
    s.push(0, EYE, Rays("e0"), eye_iteration=0)
    clock.t = 1.0
    assert s.ahead(0) == 4
    s.take(4)
    assert s.ahead(0) == 1          # no other eye work: the longest waiting, round robin among equals


def test_within_a_chunk_the_oldest_eye_iteration_then_shadows_then_photons():
    s = ChunkScheduler(1, step_rays=1000)
    s.push(0, PHOTON, Rays("p"))
    s.push(0, SHADOW, Rays("s5"), eye_iteration=5)
    s.push(0, EYE, Rays("e6"), eye_iteration=6)
    s.push(0, EYE, Rays("e5"), eye_iteration=5)
    order = [(t.kind, t.eye_iteration, _names(t)) for t in (s.take(0) for _ in range(4))]
    assert order == [(EYE, 5, ["e5"]), (EYE, 6, ["e6"]), (SHADOW, 5, ["s5"]), (PHOTON, None, ["p"])]


def test_batches_coalesce_up_to_the_step_and_counts_stay_exact():
    s = ChunkScheduler(2, step_rays=25)
    for i in range(4):
        s.push(0, PHOTON, Rays(f"p{i}", 10))
    s.push(0, EYE, Rays("big", 40), eye_iteration=0)      # over the step: taken alone
    s.push(1, SHADOW, Rays("s", 7), eye_iteration=0)
    assert (s.rays, s.eye_rays) == (87, 47)
    assert _names(s.take(0)) == ["big"]
    assert (s.rays, s.eye_rays) == (47, 7)
    assert _names(s.take(0)) == ["p0", "p1"]
    assert _names(s.take(0, photon_rays=100)) == ["p2", "p3"]
    assert 0 not in s.queues and s.rays == 7
    q = s.pop(1)
    assert [(kind, e, x.name) for kind, e, x in q.items()] == [(SHADOW, 0, "s")]
    assert s.rays == 0 and not s.has_work()


def test_photons_go_oldest_first_whatever_their_arrival():
    """A straggler of an old job that crosses a portal overtakes photons
    emitted since (ties keep their arrival order)."""
    s = ChunkScheduler(1, step_rays=10)
    s.push(0, PHOTON, Rays("new"), age=7)
    s.push(0, PHOTON, Rays("tie-first"), age=3)
    s.push(0, PHOTON, Rays("tie-second"), age=3)
    s.push(0, PHOTON, Rays("straggler"), age=1)
    assert [kind_e_x[2].name for kind_e_x in s.queues[0].items()] == ["straggler", "tie-first",
                                                                      "tie-second", "new"]
    assert [_names(s.take(0))[0] for _ in range(4)] == ["straggler", "tie-first", "tie-second", "new"]


def test_no_chunk_waits_past_a_few_dwells_behind_eye_work():
    """Eye work that keeps coming (many eye iterations in flight) must not
    starve a photon chunk: past PHOTON_WAIT_DWELLS dwells it goes first."""
    from dosppm_core.chunks.schedule import PHOTON_WAIT_DWELLS
    s, clock = _scheduler(3, dwell_s=1.0)
    s.push(2, PHOTON, Rays("p2"))
    picked = []
    for t in range(2 * PHOTON_WAIT_DWELLS + 2):
        clock.t = float(t)
        s.push(t % 2, EYE, Rays(f"e{t}"), eye_iteration=t)       # fresh eye work on chunks 0 and 1
        clock.t = t + 0.5
        k = s.pick(False)
        picked.append(k)
        while s.queues.get(k) and s.queues[k].eye_rays:
            s.take(k)
        if k == 2:
            break
    assert picked[-1] == 2 and len(picked) <= PHOTON_WAIT_DWELLS + 2, picked


def test_a_jobs_straggler_is_pursued_before_newer_photons_queued_earlier():
    """A photon job counts only when its last path has ended: the chunk a
    straggler of an old job just reached goes before one holding photons of
    newer jobs that arrived before it."""
    s, clock = _scheduler(3, dwell_s=100.0)
    s.push(2, PHOTON, Rays("job 1, first part"), age=1)
    clock.t = 1.0
    assert s.pick(False) == 2 and _names(s.take(2)) == ["job 1, first part"]
    clock.t = 5.0
    s.push(0, PHOTON, Rays("job 100"), age=100)
    clock.t = 6.0
    s.push(1, PHOTON, Rays("job 1, straggler"), age=1)
    clock.t = 7.0
    s.active = None                      # chunk 2's visit is over
    assert s.pick(False) == 1


def test_the_chunk_being_loaded_ahead_goes_next_while_it_has_work():
    """No prefetch is wasted: the chunk loading in the background goes next
    even if other work has since waited longer; never if it was swept."""
    s, clock = _scheduler(3)
    s.push(1, PHOTON, Rays("p1"))
    clock.t = 5.0
    s.push(2, PHOTON, Rays("p2"))
    clock.t = 6.0
    assert s.pick(True, loading=2) == 2
    s.take(2)
    s.push(2, PHOTON, Rays("p2 again"))
    assert s.pick(True, exclude={2}, loading=2) == 1
