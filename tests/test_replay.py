"""The replay harness (harness/replay.py, issue 13): a recorded
step's results relabelled for another package must be a results message
the wire and the server's exact accounting accept, with the recorded
deposits per path; and a real server fed by synthetic tracers must apply
every photon it committed, and report what the render cost it (issue 32:
CPU by part and bytes on the wire, from the render's start)."""
from __future__ import annotations

import numpy as np
import pytest

from dosppm_core.jobs import END_NAMES, PhotonDeposits
from harness import replay
from services import wire
from services.server.costs import FIELDS
from tests.test_wire import random_record


def _recorded(rng, paths=1000, deposits=1700):
    ends = np.zeros(len(END_NAMES), np.int64)
    ends[1:] = [300, 500, 50, 150]          # every recorded path ended, some way
    return {"deposits": random_record(PhotonDeposits, deposits, rng), "ends": ends}, paths


def test_a_relabelled_step_is_a_valid_results_message_for_the_package():
    rng = np.random.default_rng(1)
    fields, paths = _recorded(rng)
    jobs = np.repeat(np.array([40, 7, 12], np.int64), [1024, 1024, 512])
    credit = (np.array([40, 7, 12, 12], np.int64), np.array([0, 1, 2, 2], np.int64))
    ids, fed = replay._runs(jobs)
    assert ids.tolist() == [40, 7, 12] and fed.tolist() == [1024, 1024, 512]
    out = replay._relabelled(fields, paths, ids, fed, chunk=0, queue=(0, 4096), credit=credit)
    msg = wire.decode(wire.encode("results", **out))
    assert msg.credit_job.tolist() == [40, 7, 12, 12] and msg.credit_exp.tolist() == [0, 1, 2, 2]
    assert sorted(msg.job_ids.tolist()) == [7, 12, 40]
    assert dict(zip(msg.job_ids.tolist(), msg.job_fed.tolist())) == {7: 1024, 12: 512, 40: 1024}
    assert not msg.job_left.any()
    assert msg.ends.sum() == len(jobs)                       # every path of the package ended once
    assert set(np.unique(msg.deposits.job)) == {7, 12, 40}
    assert len(msg.deposits) == round(1700 * len(jobs) / 1000)   # the recorded deposits per path
    assert msg.queue_target == 4096


def test_relabelled_steps_gathered_at_the_tracer_merge_like_a_real_tracers():
    # Gathering at the tracers, the deposits stay behind and the rest is
    # accounting that merge.py holds and merges: it reads every field a
    # real tracer's results carry (a missing queue_target crashed it).
    from services.tracer.merge import MergedResults, mergeable
    rng = np.random.default_rng(2)
    fields, paths = _recorded(rng)
    held = MergedResults()
    for j in (5, 6):
        out = replay._relabelled(fields, paths, np.array([j]), np.array([256]), chunk=0, queue=(j, 100 + j),
                                 credit=(np.array([j], np.int64), np.array([0], np.int64)))
        out.pop("deposits")
        assert mergeable(out)
        held.add(out, now=0.0)
    (one,) = held.take()
    msg = wire.decode(wire.encode("results", **one))
    assert msg.job_ids.tolist() == [5, 6] and msg.ends.sum() == 512
    assert (msg.queued, msg.queue_target) == (6, 106)       # the latest queue


def test_a_replayed_job_message_returns_every_path_and_all_its_credit_in_step_sized_results():
    # slow_link.py's synthetic tracers answer photon job messages at once:
    # a results message per recorded step's paths, which together end
    # every photon once and return the message's credit exactly.
    from dosppm_core.scene import builtin
    from services.tracer.state import SERVER
    from tests.helpers.chunks import MemoryChunks, root_box, uniform_tree
    from tests.helpers.credit import credit_sum
    scene = builtin.make("cornell-box")
    t = replay.ReplayState("inproc://t", MemoryChunks(scene, uniform_tree(root_box(scene), (1, 1, 1))), 10, seed=7)
    rng = np.random.default_rng(3)
    try:
        t.replay_emission = True
        t.recorded = [_recorded(rng, paths=1000)] * replay.RECORDED_STEPS
        ids, counts = np.array([40, 41, 42], np.int64), np.array([1500, 2500, 700], np.int64)
        credit = (np.array([40, 41, 42, 42], np.int64), np.array([0, 0, 1, 1], np.int64))
        out = t.emit(ids, np.arange(3), counts, np.zeros((2, 3)), credit)
    finally:
        t.close()
    msgs = [wire.decode(wire.encode("results", **o.fields)) for o in out]
    assert all(o.dest == SERVER for o in out) and len(msgs) == 5          # 4,700 paths, 1,000 a step
    assert [int(m.ends.sum()) for m in msgs] == [1000] * 4 + [700]
    assert [len(m.deposits) for m in msgs] == [1700] * 4 + [1190]     # the recorded deposits per path
    fed = {}
    for m in msgs:
        for j, n in zip(m.job_ids.tolist(), m.job_fed.tolist()):
            fed[j] = fed.get(j, 0) + n
    assert fed == {40: 1500, 41: 2500, 42: 700}
    # Each job's credit, all of it, once (the message brought 1 each).
    assert credit_sum([(m.credit_job, m.credit_exp) for m in msgs]) == {40: 1, 41: 1, 42: 1}


@pytest.fixture(scope="module")
def replayed(tmp_path_factory):
    """One short replayed render's server summary, shared by the tests below."""
    return replay.run("cornell-box", tracers=1, seconds=4.0, work=str(tmp_path_factory.mktemp("replay")))


@pytest.mark.slow
def test_a_server_fed_by_synthetic_tracers_applies_what_it_committed(replayed):
    s = replayed
    c = s["counters"]
    assert s["replay_tracers"][0]["replayed_steps"] > 0      # past the recorded steps: replaying
    assert c["photons_committed"] > 0
    assert s["photons_applied"] == c["photons_committed"]
    f = replay.figures(s, per_core=1e5)
    assert f["photons_per_server_cpu_s"] > 0 and f["tracer_photons_per_core_s"] > 0


@pytest.mark.slow
def test_the_server_reports_what_the_render_cost_it_by_part(replayed):
    s, tol = replayed, 0.05        # CPU seconds: marks are read one after the other
    r = s["render_costs"]
    assert set(FIELDS) <= set(r) and all(r[k] >= 0 for k in FIELDS)
    # The parts on the loop's thread are within it, and it and the
    # statistics thread within the process's CPU since the start.
    assert r["job_making_cpu_s"] + r["held_cpu_s"] <= r["loop_cpu_s"] + tol
    assert r["loop_cpu_s"] + r["statistics_cpu_s"] <= r["cpu_s"] + tol
    assert r["job_making_cpu_s"] > 0 and r["held_cpu_s"] > 0 and r["statistics_cpu_s"] > 0
    # Start-up left out: less than the whole process's CPU (loading the store at least).
    assert r["cpu_s"] < s["cpu_s"]
    assert 0 < r["bytes_in"] <= s["bytes_in"] and 0 < r["bytes_out"] <= s["bytes_out"]
    f = replay.figures(s, per_core=1e5)
    assert f["bytes_in_per_photon"] > 0 and f["bytes_out_per_photon"] > 0
    assert f["server_cpu_us_per_photon"] > 0
    assert min(f[k] for k in ("job_making_share", "held_share", "statistics_share")) >= 0


def test_the_shares_of_server_cpu_add_up():
    costs = dict(cpu_s=10.0, loop_cpu_s=6.0, job_making_cpu_s=2.0, held_cpu_s=1.0, statistics_cpu_s=3.0,
                 bytes_in=5_000, bytes_out=1_000)
    counters = {"photons_committed": 1000, "photons_emitted": 1250, "results": 10, "deposits_received": 4000}
    s = {"counters": counters, "seconds": 5.0, "cpu_s": 12.0, "render_costs": costs}
    f = replay.figures(s, per_core=50.0)
    assert f["server_cpu_s"] == 10.0 and f["server_cpu_us_per_photon"] == pytest.approx(1e4)
    assert f["tracer_cores_per_server_core"] == pytest.approx(100 / 50)      # start-up excluded
    assert (f["bytes_in_per_photon"], f["bytes_out_per_photon"]) == (4.0, 0.8)
    assert (f["job_making_share"], f["held_share"], f["loop_other_share"]) == pytest.approx((0.2, 0.1, 0.3))
    assert f["loop_share_of_cpu"] == pytest.approx(0.6) and f["statistics_share"] == pytest.approx(0.3)
    parts = ("job_making_share", "held_share", "loop_other_share", "statistics_share", "other_threads_share")
    assert sum(f[k] for k in parts) == pytest.approx(1.0)
    assert "| server CPU per photon applied" in replay.report(
        {"scene": "x", "tracers": 1, "seconds": 5.0, "replay": dict(f, repeats=1)})


def test_a_server_that_does_not_end_in_time_is_killed_with_its_tracers():
    """A replay server that hung once outlived its harness by 1.5 h: the
    harness gives up after `wait_s` and no process it started lives on."""
    import subprocess
    import sys
    sleeper = [sys.executable, "-c", "import time; time.sleep(120)"]
    server = subprocess.Popen(sleeper)
    tracers = [subprocess.Popen(sleeper, stdout=subprocess.PIPE, text=True) for _ in range(2)]
    with pytest.raises(RuntimeError, match="did not end within"):
        replay._awaited(server, tracers, wait_s=0.5)
    assert server.poll() is not None and all(t.poll() is not None for t in tracers)


def test_replayed_epochs_answer_with_a_recorded_sums_answer_and_keep_no_deposit():
    # slow_link.py's synthetic tracers: past RECORDED_EPOCHS real gathers,
    # an epoch's sums are a recorded answer's rows cycled to the hit points.
    from types import SimpleNamespace
    from dosppm_core.jobs import HitPoints
    from services.tracer.epochs import EpochDeposits
    rng = np.random.default_rng(4)
    ep = replay.ReplayedEpochs(EpochDeposits(8, materials=None))
    ep.recorded = [dict(deposits=70, flux=np.ones(3), m=np.array([0.0, 2.0, 1.0]), phi=np.arange(9.0).reshape(3, 3))
                   for _ in range(replay.RECORDED_EPOCHS)]
    assert not ep.keeps_deposits
    ep.add(random_record(PhotonDeposits, 50, rng))
    assert ep.rows == 0                                        # nothing held once replaying
    ep.set_hit_points(3, random_record(HitPoints, 7, rng))
    msg = SimpleNamespace(epoch=9, epochs=1, phase="sums", hits_version=3)
    out = ep.reply(msg)
    got = wire.decode(wire.encode("epoch_sums", **out))
    assert got.epoch == 9 and got.deposits == 70
    from services.tracer.epochs import dense_sums
    m, phi = dense_sums(7, got.m, got.phi, got.fields.get("rows"))
    assert m.tolist() == [0, 2, 1, 0, 2, 1, 0]
    assert np.array_equal(phi[4], [3.0, 4.0, 5.0])
    # Three epochs merged into one gather: three recorded answers' worth.
    got = wire.decode(wire.encode("epoch_sums", **ep.reply(SimpleNamespace(epoch=10, epochs=3, phase="sums",
                                                                           hits_version=3))))
    assert got.epoch == 10 and got.deposits == 210 and got.flux.tolist() == [3, 3, 3]
    assert dense_sums(7, got.m, got.phi, got.fields.get("rows"))[0].tolist() == [0, 6, 3, 0, 6, 3, 0]
