"""The chunk scheduler that OSPPM and every tracer share (issue 31): eye
work goes first in the choice of chunk, the prefetch and the batch; photon
work keeps round robin with a bounded dwell; batches coalesce up to the
step size; the counts stay exact."""
from __future__ import annotations

from dosppm_core.chunks.schedule import EYE, PHOTON, SHADOW, ChunkScheduler


class Rays:
    """A package of `n` rays, named for the asserts."""

    def __init__(self, name: str, n: int = 10):
        self.name, self.n = name, n

    def __len__(self) -> int:
        return self.n


def _names(taken) -> list[str]:
    return [x.name for x in taken.items]


def test_a_chunk_that_eye_rays_wait_for_is_picked_before_photon_chunks():
    s = ChunkScheduler(4, step_rays=100)
    for k in (0, 1, 3):
        s.push(k, PHOTON, Rays(f"p{k}"))
    s.push(2, EYE, Rays("e2"), eye_iteration=0)
    assert s.pick(False, 0.0) == 2
    assert s.take(2).kind == EYE
    # Eye work gone: photons again, round robin after the chunk just traced.
    assert s.pick(False, 0.0) == 3


def test_the_active_chunk_keeps_its_eye_work_and_photons_wait_behind_it():
    s = ChunkScheduler(3, step_rays=10)
    s.push(0, PHOTON, Rays("p0"))
    s.push(1, EYE, Rays("e1a"), eye_iteration=0)
    s.push(1, EYE, Rays("e1b"), eye_iteration=0)
    s.push(2, SHADOW, Rays("s2"), eye_iteration=0)
    assert s.pick(False, 0.0) == 1 and _names(s.take(1)) == ["e1a"]
    assert s.pick(False, 0.0) == 1 and _names(s.take(1)) == ["e1b"]
    assert s.pick(False, 0.0) == 2 and s.take(2).kind == SHADOW
    assert s.pick(False, 0.0) == 0 and s.take(0).kind == PHOTON
    assert s.pick(False, 0.0) is None and not s.has_work()


def test_within_a_chunk_the_oldest_eye_iteration_then_shadows_then_photons():
    s = ChunkScheduler(1, step_rays=1000)
    s.push(0, PHOTON, Rays("p"))
    s.push(0, SHADOW, Rays("s5"), eye_iteration=5)
    s.push(0, EYE, Rays("e6"), eye_iteration=6)
    s.push(0, EYE, Rays("e5"), eye_iteration=5)
    order = [(t.kind, t.eye_iteration, _names(t)) for t in (s.take(0) for _ in range(4))]
    assert order == [(EYE, 5, ["e5"]), (EYE, 6, ["e6"]), (SHADOW, 5, ["s5"]), (PHOTON, None, ["p"])]


def test_photons_dwell_on_the_active_chunk_only_while_not_all_fit():
    def visits(all_fit: bool) -> list[int]:
        s = ChunkScheduler(2, step_rays=10, dwell_s=3.0)
        for k in (0, 1):
            for i in range(6):
                s.push(k, PHOTON, Rays(f"p{k}{i}"))
        seen = []
        for t in range(8):                   # a step a second
            k = s.pick(all_fit, float(t))
            s.take(k)
            seen.append(k)
        return seen
    assert visits(all_fit=False) == [0, 0, 0, 1, 1, 1, 0, 0]     # 3 s on each
    assert visits(all_fit=True) == [0, 1, 0, 1, 0, 1, 0, 1]


def test_eye_work_cuts_a_photon_dwell_short():
    s = ChunkScheduler(2, step_rays=10, dwell_s=100.0)
    for i in range(5):
        s.push(0, PHOTON, Rays(f"p{i}"))
    assert s.pick(False, 0.0) == 0
    s.take(0)
    s.push(1, EYE, Rays("e"), eye_iteration=0)
    assert s.pick(False, 0.0) == 1


def test_the_prefetch_is_the_next_chunk_eye_rays_wait_for():
    s = ChunkScheduler(5, step_rays=10)
    s.push(1, PHOTON, Rays("p1"))
    s.push(2, PHOTON, Rays("p2"))
    s.push(4, EYE, Rays("e4"), eye_iteration=0)
    s.push(0, EYE, Rays("e0"), eye_iteration=0)
    assert s.ahead(0) == 4
    s.take(4)
    assert s.ahead(0) == 1          # no other eye work: the next chunk with any


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
