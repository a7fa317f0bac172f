"""The gather split for tracers (issue 32 step 3): gathering a batch's
deposits into per-hit-point sums (`gather_sums`, `pilot_sums`) and applying
the sums (`PixelStatistics.apply_sums`, `fit_from_pilot`) is today's update
(`apply_photons`) exactly when one holder has the whole batch, and the
same within float64 summation order when tracers hold parts of it."""
import numpy as np

from dosppm_core.jobs import HitPoints, PhotonDeposits
from dosppm_core.scene.model import Material, MaterialTable
from dosppm_core.sppm.statistics import PixelStatistics, gather_sums, pilot_radius, pilot_sums

MATERIALS = MaterialTable.from_materials([
    Material("matte", reflectance=(0.8, 0.5, 0.3)),
    Material("satin", kind="glossy", reflectance=(0.6, 0.7, 0.9), roughness=0.3),
])
SIDE = 24


def _unit(v):
    return (v / np.linalg.norm(v, axis=-1, keepdims=True)).astype(np.float32)


def _hits(rng):
    n = SIDE * SIDE
    pos = np.c_[rng.uniform(0, 1, (n, 2)), np.zeros(n)].astype(np.float32)
    up = np.tile(np.float32([0, 0, 1]), (n, 1))
    return HitPoints(position=pos, normal=up, outgoing=_unit(rng.normal(size=(n, 3)) * [1, 1, 0] + [0, 0, 2]),
                     weight=rng.uniform(0.2, 1, (n, 3)).astype(np.float32),
                     material=rng.integers(0, 2, n).astype(np.int32),
                     pixel=rng.permutation(n).astype(np.int32))


def _deposits(rng, n):
    pos = np.c_[rng.uniform(0, 1, (n, 2)), rng.uniform(-1e-3, 1e-3, n)].astype(np.float32)
    return PhotonDeposits(position=pos, incoming=_unit(rng.normal(size=(n, 3)) * [1, 1, 0] + [0, 0, 1.5]),
                          flux=rng.uniform(0.1, 1, (n, 3)).astype(np.float32))


def _stats(hits):
    s = PixelStatistics(SIDE, SIDE, None, 0.7)
    s.fit_radii(hits.pixel, pilot_radius(hits), np.full(len(hits), 1e-3))
    s.replace_hit_points(hits, (np.zeros(0, np.int32), np.zeros((0, 3))))
    return s


def _by_sums(s, holders, emitted):
    """One batch held by `holders` (lists of parts): the pilot and the
    gather each holder runs, summed, then applied, as the server does."""
    hp, total = s.hit_points, sum(len(p) for h in holders for p in h)
    request = s.pilot_request()
    if request is not None:
        fresh, r_pilot, most = request
        m = chosen = 0
        for h in holders:
            dm, dc = pilot_sums(h, hp.take(fresh), r_pilot, MATERIALS, 2, most, total)
            m, chosen = m + dm, chosen + dc
        s.fit_from_pilot(fresh, r_pilot, m, chosen)
    m = phi = 0
    for h in holders:
        dm, dphi = gather_sums(h, hp, s.radius[hp.pixel], MATERIALS, threads=2)
        m, phi = m + dm, phi + dphi
    s.apply_sums(hp.pixel, m, phi, emitted)


def _batches(seed, count=3, n=60_000):
    rng = np.random.default_rng(seed)
    return _hits(rng), [_deposits(rng, n) for _ in range(count)]


def test_sums_of_one_holder_equal_the_update_bit_for_bit():
    hits, batches = _batches(5)
    a, b = _stats(hits), _stats(hits)
    for k, d in enumerate(batches):
        a.apply_photons([d.slice(0, 1000), d.slice(1000, len(d))], 1000 + k, MATERIALS)
        _by_sums(b, [[d.slice(0, 1000), d.slice(1000, len(d))]], 1000 + k)
    assert a.photons_emitted == b.photons_emitted
    for name in ("radius", "photon_count", "tau", "fitted"):
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name), err_msg=name)
    np.testing.assert_array_equal(a.radiance(), b.radiance())


def test_sums_of_three_holders_equal_the_update_up_to_summation_order():
    hits, batches = _batches(6)
    a, b = _stats(hits), _stats(hits)
    for k, d in enumerate(batches):
        a.apply_photons(d, 900, MATERIALS)
        cut = [0, 7_000, 31_000, len(d)]
        _by_sums(b, [[d.slice(cut[i], cut[i + 1])] for i in range(3)], 900)
    np.testing.assert_array_equal(a.fitted, b.fitted)
    np.testing.assert_array_equal(a.photon_count, b.photon_count)    # M are whole counts
    np.testing.assert_allclose(a.radius, b.radius, rtol=1e-12)
    np.testing.assert_allclose(a.tau, b.tau, rtol=1e-9, atol=1e-12)
    assert (a.photon_count > 0).mean() > 0.9


def test_empty_sums_count_the_photons_emitted():
    hits, _ = _batches(7, count=0)
    s = _stats(hits)
    s.apply_sums(np.zeros(0, np.int32), np.zeros(0), np.zeros((0, 3)), 4096)
    assert s.photons_emitted == 4096 and not s.photon_count.any()
