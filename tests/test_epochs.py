"""A tracer's share of the gather (services/tracer/epochs.py): deposits held
by epoch, culled to their own job's box, gathered at the hit points and
radii a request names, exactly as the library gathers the same deposits;
dropped epochs keep nothing; requests it cannot answer fail naming the field."""
import numpy as np
import pytest

from services import wire
from services.culling import within_own_boxes
from services.tracer.epochs import EpochDeposits, dense_sums, sparse_sums
from dosppm_core.sppm.statistics import gather_sums, pilot_sums
from tests.test_epoch_sums import MATERIALS, _deposits, _hits

JOBS_PER_EPOCH = 4


def _request(**fields):
    return wire.decode([bytes(f) for f in wire.encode("gather", **fields)])


def _setup(seed=3):
    rng = np.random.default_rng(seed)
    hits, d = _hits(rng), _deposits(rng, 20_000)
    d.job[:] = rng.integers(0, 3 * JOBS_PER_EPOCH, len(d))
    ids = np.arange(3 * JOBS_PER_EPOCH, dtype=np.int64)
    boxes = np.tile(np.array([[0.0, 0.0, -1.0], [1.0, 1.0, 1.0]]), (len(ids), 1, 1))
    boxes[1] = [[0.0, 0.0, -1.0], [0.5, 0.5, 1.0]]      # job 1 was sent with a smaller box
    held = EpochDeposits(JOBS_PER_EPOCH, MATERIALS, threads=2)
    for k in range(0, len(d), 3000):                    # as steps make them
        held.add(d.slice(k, min(len(d), k + 3000)))
    held.set_hit_points(0, hits)
    return held, hits, d, ids, boxes


def _epoch(d, ids, boxes, e):
    mine = d.take((d.job // JOBS_PER_EPOCH) == e)
    part = slice(e * JOBS_PER_EPOCH, (e + 1) * JOBS_PER_EPOCH)
    return within_own_boxes(mine, (ids[part], None, None, boxes[part])), ids[part], boxes[part]


def test_each_phase_answers_what_the_library_computes_on_the_epoch():
    held, hits, d, ids, boxes = _setup()
    own, jids, jboxes = _epoch(d, ids, boxes, 0)
    assert len(own) < int(np.sum(d.job < JOBS_PER_EPOCH))      # the own-box cull took some of job 1
    jobs = dict(epoch=0, hits_version=0, job_ids=jids, job_boxes=jboxes)
    count = held.reply(_request(phase="count", rows=np.zeros(0, np.int64), radius=np.zeros(0), **jobs))
    assert count["deposits"] == len(own)
    np.testing.assert_array_equal(count["flux"], own.flux.sum(0, dtype=np.float64))
    rows, r = np.arange(0, len(hits), 7, dtype=np.int64), np.full(-(-len(hits) // 7), 0.05)
    pilot = held.reply(_request(phase="pilot", total=len(own), most=2000, rows=rows, radius=r, **jobs))
    m, chosen = pilot_sums([own], hits.take(rows), r, MATERIALS, 2, 2000, len(own))
    np.testing.assert_array_equal(pilot["m"], m)
    assert pilot["chosen"] == chosen > 0
    radius = np.full(len(hits), 0.04)
    sums = held.reply(_request(phase="sums", rows=np.arange(len(hits)), radius=radius, **jobs))
    m, phi = gather_sums([own], hits, radius, MATERIALS, threads=2)
    got = dense_sums(len(hits), sums["m"], sums["phi"], sums.get("rows"))
    np.testing.assert_array_equal(got[0], m)
    np.testing.assert_array_equal(got[1], phi)
    assert 0 not in held.held and 0 not in held._culled and 1 in held.held   # gathered: dropped


def test_a_dropped_epoch_keeps_nothing_not_even_late_deposits():
    held, hits, d, ids, boxes = _setup()
    held.drop(1)
    held.add(d.take((d.job // JOBS_PER_EPOCH) == 1))
    assert 1 not in held.held and 2 in held.held


def test_sums_go_sparse_only_when_smaller():
    m = np.zeros(100)
    m[[3, 50]] = 2.0
    phi = np.outer(m, [1.0, 2.0, 3.0])
    s = sparse_sums(m, phi)
    assert s["rows"].tolist() == [3, 50]
    np.testing.assert_array_equal(dense_sums(100, s["m"], s["phi"], s["rows"])[1], phi)
    assert "rows" not in sparse_sums(np.ones(100), np.ones((100, 3)))


def test_a_request_for_hit_points_it_lacks_fails_naming_the_field():
    held, hits, d, ids, boxes = _setup()
    with pytest.raises(ValueError, match="'hits_version'"):
        held.reply(_request(epoch=0, phase="sums", hits_version=5, job_ids=ids[:4], job_boxes=boxes[:4],
                            rows=np.arange(len(hits)), radius=np.ones(len(hits))))
    with pytest.raises(ValueError, match="'rows'"):
        held.reply(_request(epoch=0, phase="sums", hits_version=0, job_ids=ids[:4], job_boxes=boxes[:4],
                            rows=np.arange(3), radius=np.ones(3)))
