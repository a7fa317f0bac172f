"""Equal time means equal (issue 34): a peer renderer's sample count is
calibrated to each budget by pilots (`evaluate.calibrated`), re-sized
when a run misses by more than 5%, and a run that cannot make its
budget stands at its measured time, which the tables then print."""
from __future__ import annotations

import math

import pytest

from harness import evaluate
from harness.suites import Sample


def _renderer(fixed: float, per_sample, log: list):
    """A fake run(n): `fixed` + n x per_sample(run index) seconds, logged."""
    def run(n: int):
        seconds = fixed + n * per_sample(len(log))
        log.append((n, seconds))
        return seconds, 10 * n, f"image of {n}"
    return run


def test_pilots_then_one_run_per_budget_each_on_it():
    log = []
    stops = evaluate.calibrated(_renderer(0.3, lambda _i: 0.01, log), [1.0, 2.0, 4.0])
    assert [b for b, *_ in stops] == [1.0, 2.0, 4.0]
    assert [n for n, _ in log] == [1, 2, 70, 170, 370]     # two pilots, then (budget - 0.3 s) / 10 ms each
    assert all(s == pytest.approx(b) for b, s, *_ in stops)
    assert [p for _, _, p, _ in stops] == [700, 1700, 3700] and stops[0][3] == "image of 70"


def test_a_run_that_misses_is_resized_by_its_own_rate():
    # The renderer slows down 2x after its pilots (a cold cache, a busy
    # machine): the first sized run takes twice its budget, the next lands.
    log = []
    slow = lambda i: 0.01 if i < 4 else 0.02      # noqa: E731
    stops = evaluate.calibrated(_renderer(0.0, slow, log), [0.5])
    assert [n for n, _ in log] == [1, 2, 4, 8, 50, 23, 25]      # pilots to a tenth of 0.5 s; 1 s, 0.46 s, 0.5 s
    assert stops[0][1] == pytest.approx(0.5) and not evaluate.off_budget(0.5, stops[0][1])


def test_a_budget_one_sample_cannot_fit_stands_at_its_measured_time():
    log = []
    stops = evaluate.calibrated(_renderer(2.0, lambda _i: 0.5, log), [1.0, 8.0])
    (b0, s0, *_), (b1, s1, *_) = stops
    assert (b0, s0) == (1.0, 2.5) and evaluate.off_budget(b0, s0)      # one sample: 2.5 s
    assert s1 == pytest.approx(8.0)
    assert sum(1 for n, _ in log if n == 1) == 2        # the pilot, and the one run the 1 s budget got


def test_tables_give_the_measured_time_of_a_run_off_its_budget():
    ev = evaluate.Evaluation("x", 8.0)
    ev.samples = [Sample("box", "sppm-grid", 8.0, 8.1, 0, True, relmse=0.01, bias=0.0),
                  Sample("box", "mitsuba-path", 8.0, 9.1, 0, True, relmse=0.02, bias=0.0)]
    rows = evaluate.relmse_table(ev)
    assert "0.01 (+0.0%) |" in rows[-1] and "0.02 (+0.0%) at 9.1 s" in rows[-1]
    claims = evaluate.claims(ev)
    assert any("9.1 s" in c for c in claims), claims
    assert math.isclose(evaluate.ON_BUDGET, 0.05)


def test_dosppm_counts_its_start_up_and_sizes_its_time_by_the_last_run(monkeypatch):
    # A render whose processes and store take 3 s before its --time starts.
    asked = []

    def fake_run(spec, scene, render_s, seed, work):
        asked.append(render_s)
        return 3.0 + render_s, 1000, None
    monkeypatch.setattr(evaluate, "_dosppm_run", fake_run)
    scene = type("S", (), {"source": "", "name": "box"})()
    stops = evaluate._dosppm(scene, [1.0, 2.0, 8.0], 1, "")
    assert asked == [1.0, evaluate.MIN_DOSPPM_TIME_S, 5.0]       # 8 s less the 3 s start-up
    assert [s for _, s, _, _ in stops] == [4.0, 3.25, 8.0]        # whole-process seconds
    assert [evaluate.off_budget(b, s) for b, s, _, _ in stops] == [True, True, False]
