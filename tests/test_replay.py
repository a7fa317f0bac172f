"""The replay harness (services/evaluation/replay.py, issue 13): a recorded
step's results relabelled for another package must be a results message
the wire and the server's exact accounting accept, with the recorded
deposits per path; and a real server fed by synthetic tracers must apply
every photon it committed."""
from __future__ import annotations

import numpy as np
import pytest

from dosppm_core.jobs import END_NAMES, PhotonDeposits
from services import wire
from services.evaluation import replay
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
    out = replay._relabelled(fields, paths, jobs, chunk=0, queued=0, credit=credit)
    msg = wire.decode(wire.encode("results", **out))
    assert msg.credit_job.tolist() == [40, 7, 12, 12] and msg.credit_exp.tolist() == [0, 1, 2, 2]
    assert sorted(msg.job_ids.tolist()) == [7, 12, 40]
    assert dict(zip(msg.job_ids.tolist(), msg.job_fed.tolist())) == {7: 1024, 12: 512, 40: 1024}
    assert not msg.job_left.any()
    assert msg.ends.sum() == len(jobs)                       # every path of the package ended once
    assert set(np.unique(msg.deposits.job)) == {7, 12, 40}
    assert len(msg.deposits) == round(1700 * len(jobs) / 1000)   # the recorded deposits per path


@pytest.mark.slow
def test_a_server_fed_by_synthetic_tracers_applies_what_it_committed(tmp_path):
    s = replay.run("cornell-box", tracers=1, seconds=4.0, work=str(tmp_path))
    c = s["counters"]
    assert s["replay_tracers"][0]["replayed_steps"] > 0      # past the recorded steps: replaying
    assert c["photons_committed"] > 0
    assert s["photons_applied"] == c["photons_committed"]
    f = replay.figures(s, per_core=1e5)
    assert f["photons_per_server_cpu_s"] > 0 and f["tracer_photons_per_core_s"] > 0
