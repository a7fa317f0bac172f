"""Job records: partitioning by key (the routing of rays to chunks and
tracers) against a plain stable sort."""
import numpy as np
import pytest

from dosppm_core.jobs import HitPoints, RayBatch


def _batch(n, seed=0):
    rng = np.random.default_rng(seed)
    f3 = lambda: rng.random((n, 3), dtype=np.float32)  # noqa: E731
    return RayBatch(f3(), f3(), f3(), rng.integers(0, 99, n).astype(np.int32),
                    rng.integers(0, 9, n).astype(np.int32), rng.integers(0, 2**63, n).astype(np.uint64),
                    tmin=rng.random(n, dtype=np.float32), job=np.arange(n, dtype=np.int64))


def _expect(batch, keys, rows=None):
    rows = np.arange(len(batch)) if rows is None else rows
    return {int(k): batch.take(rows[keys == k]) for k in np.unique(keys)}


def _assert_same(got, want):
    assert sorted(got) == sorted(want)
    for k in want:
        for name, column in want[k].arrays().items():
            np.testing.assert_array_equal(getattr(got[k], name), column, err_msg=f"{k} {name}")


@pytest.mark.parametrize("span", [3, 40, 1 << 17])   # counting sort, and argsort for wide keys
def test_partition_keeps_row_order_within_each_key(span):
    batch = _batch(5000)
    keys = np.random.default_rng(1).integers(-1, span, len(batch)).astype(np.int32)
    _assert_same(batch.partition(keys), _expect(batch, keys))


def test_partition_of_some_rows_with_a_column_replaced():
    batch = _batch(3000)
    rng = np.random.default_rng(2)
    rows = np.sort(rng.choice(len(batch), 700, replace=False))
    keys = rng.integers(0, 5, len(rows)).astype(np.int32)
    tmin = rng.random(len(batch), dtype=np.float32)
    got = batch.partition(keys, rows=rows, replace={"tmin": tmin})
    want = _expect(batch, keys, rows)
    for k, part in want.items():
        part.tmin = tmin[rows[keys == k]]
    _assert_same(got, want)
    assert not np.shares_memory(got[int(keys[0])].origin, batch.origin)


def test_a_single_key_is_the_record_itself():
    batch = _batch(100)
    got = batch.partition(np.full(len(batch), 7, np.int32))
    assert list(got) == [7] and got[7] is batch
    assert batch.partition(np.empty(0, np.int32)) == {}


def test_concat_of_one_part_is_that_part_and_of_several_is_their_rows():
    a, b = _batch(10, 1), _batch(20, 2)
    assert RayBatch.concat([a]) is a
    both = RayBatch.concat([a, None, b])
    np.testing.assert_array_equal(both.origin, np.concatenate([a.origin, b.origin]))
    assert len(RayBatch.concat([])) == 0


def _hits(n, frame):
    z = np.zeros((n, 3), np.float32)
    return HitPoints(position=z + np.arange(n, dtype=np.float32)[:, None], normal=z, outgoing=z, weight=z,
                     material=np.zeros(n, np.int32), pixel=np.arange(n, dtype=np.int32),
                     frame=np.ones((n, 5), np.float32) if frame else None)


def test_an_optional_column_stays_absent_and_fills_with_zeros_beside_one_present():
    """HitPoints.frame: absent in the empty record and through take, slice
    and partition; concat of parts without it has none, and with it in
    some parts the others' rows get zeros."""
    assert HitPoints.empty().frame is None
    plain = _hits(4, frame=False)
    assert plain.take([2, 0]).frame is None and plain.slice(1, 3).frame is None
    assert all(p.frame is None for p in plain.partition(np.array([0, 1, 0, 1])).values())
    assert HitPoints.concat([plain, HitPoints.empty(), plain]).frame is None
    mixed = HitPoints.concat([plain, _hits(2, frame=True), HitPoints.empty()])
    np.testing.assert_array_equal(mixed.frame, np.r_[np.zeros((4, 5)), np.ones((2, 5))])
    np.testing.assert_array_equal(mixed.take([5, 0]).frame, [[1] * 5, [0] * 5])
