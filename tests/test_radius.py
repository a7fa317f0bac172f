"""The initial radius, fitted per hit point to the photon density
(`PixelStatistics.fit_radii` and the pilot gather of the first batch that
reaches a pixel), against the densities it was given."""
import math

import numpy as np
import pytest

from dosppm_core.jobs import HitPoints, PhotonDeposits
from dosppm_core.scene.model import Material, MaterialTable
from dosppm_core.sppm.statistics import PILOT_DIAGONAL, RADIUS_SHARE, PixelStatistics, pilot_radius

MATTE = MaterialTable.from_materials([Material("matte", reflectance=(0.5, 0.5, 0.5))])
ALPHA = 0.7
SIDE = 100                                  # hit points on a SIDE x SIDE lattice over [0.25, 0.75]^2


def _floor_hit_points(lo=0.25, hi=0.75) -> HitPoints:
    """A lattice of hit points on the floor z = 0, facing up, one per pixel."""
    g = np.linspace(lo, hi, SIDE)
    x, y = np.meshgrid(g, g)
    n = SIDE * SIDE
    pos = np.c_[x.ravel(), y.ravel(), np.zeros(n)].astype(np.float32)
    up = np.tile(np.float32([0, 0, 1]), (n, 1))
    return HitPoints(position=pos, normal=up, outgoing=up, weight=np.ones((n, 3), np.float32),
                     material=np.zeros(n, np.int32), pixel=np.arange(n, dtype=np.int32))


def _floor_deposits(rng, n, x_range=(0.25, 0.75)) -> PhotonDeposits:
    """`n` photons uniform over [x_range] x [0.25, 0.75] of the floor, from above."""
    pos = np.c_[rng.uniform(*x_range, n), rng.uniform(0.25, 0.75, n), np.zeros(n)].astype(np.float32)
    down = np.tile(np.float32([0, 0, 1]), (n, 1))
    return PhotonDeposits(position=pos, incoming=down, flux=np.ones((n, 3), np.float32))


def _stats(hits: HitPoints, radius=None, min_radius=1e-4) -> PixelStatistics:
    stats = PixelStatistics(SIDE, SIDE, radius, ALPHA)
    if radius is None:
        stats.fit_radii(hits.pixel, pilot_radius(hits), np.full(len(hits), min_radius))
    stats.replace_hit_points(hits, (np.zeros(0, np.int32), np.zeros((0, 3), np.float32)))
    return stats


def _fitted(share_per_area: float) -> float:
    """The radius whose disc holds RADIUS_SHARE hit points' fair share of
    the deposits (1 / hit points each), where `share_per_area` of them fall
    on a unit of area; after the first update's shrink (R^2 times alpha)."""
    r0 = math.sqrt(RADIUS_SHARE / (SIDE * SIDE) / (math.pi * share_per_area))
    return r0 * math.sqrt(ALPHA)


def test_the_pilot_radius_is_a_fiftieth_of_the_hit_points_extent():
    hits = _floor_hit_points()
    assert pilot_radius(hits) == pytest.approx(0.5 * math.sqrt(2) * PILOT_DIAGONAL, rel=1e-6)


def test_a_uniform_density_gives_the_radius_that_holds_the_target_share():
    rng = np.random.default_rng(1)
    hits, n = _floor_hit_points(), 400_000
    stats = _stats(hits)
    stats.apply_photons(_floor_deposits(rng, n), n, MATTE)
    expect = _fitted(1 / 0.25)
    assert expect < pilot_radius(hits) * math.sqrt(ALPHA)       # the fit, not the clamp
    assert np.median(stats.radius) == pytest.approx(expect, rel=0.03)
    # Each pixel's own fit, from ~60 pilot photons: within a few tens of percent.
    assert np.percentile(np.abs(stats.radius / expect - 1), 90) < 0.3


def test_a_region_four_times_as_dense_starts_at_half_the_radius():
    rng = np.random.default_rng(2)
    hits = _floor_hit_points()
    dense = _floor_deposits(rng, 400_000, (0.25, 0.5))          # 4x the density of...
    sparse = _floor_deposits(rng, 100_000, (0.5, 0.75))         # ...this half
    stats = _stats(hits)
    stats.apply_photons(PhotonDeposits.concat([dense, sparse]), 500_000, MATTE)
    x = hits.position[:, 0]
    left, right = np.median(stats.radius[x < 0.45]), np.median(stats.radius[x > 0.55])
    assert right / left == pytest.approx(2.0, rel=0.06)


def test_pixels_no_photon_reaches_keep_the_pilot_radius_until_one_does():
    rng = np.random.default_rng(3)
    hits = _floor_hit_points()
    stats = _stats(hits)
    pilot = pilot_radius(hits)
    stats.apply_photons(_floor_deposits(rng, 200_000, (0.25, 0.4)), 200_000, MATTE)
    dark = hits.position[:, 0] > 0.5
    assert np.all(stats.photon_count[dark] == 0) and np.all(stats.tau[dark] == 0)
    np.testing.assert_array_equal(stats.radius[dark], pilot)
    # A later batch that reaches them fits them to its own density.
    stats.apply_photons(_floor_deposits(rng, 400_000), 400_000, MATTE)
    assert np.median(stats.radius[dark]) == pytest.approx(_fitted(1 / 0.25), rel=0.05)


def test_a_fitted_radius_never_goes_below_its_floor_or_above_the_pilot():
    rng = np.random.default_rng(4)
    hits = _floor_hit_points()
    stats = _stats(hits, min_radius=0.012)          # above the fit (~0.008), below the pilot (0.0141)
    stats.apply_photons(_floor_deposits(rng, 400_000), 400_000, MATTE)
    shrunk = math.sqrt(ALPHA)
    assert np.all(stats.radius >= 0.012 * shrunk * (1 - 1e-6))
    assert np.all(stats.radius <= pilot_radius(hits) * shrunk * (1 + 1e-6))
    inside = np.all(np.abs(hits.position[:, :2] - 0.5) < 0.25 - pilot_radius(hits), axis=1)
    np.testing.assert_allclose(stats.radius[inside], 0.012 * shrunk, rtol=1e-6)   # the fit, floored
    sparse = _stats(hits)                           # 100 deposits: almost none in reach
    sparse.apply_photons(_floor_deposits(rng, 100), 100, MATTE)
    assert np.all(sparse.radius <= pilot_radius(hits) + 1e-12)


def test_a_given_radius_is_not_fitted():
    rng = np.random.default_rng(5)
    hits = _floor_hit_points()
    stats = _stats(hits, radius=0.02)
    stats.apply_photons(_floor_deposits(rng, 400_000), 400_000, MATTE)
    np.testing.assert_allclose(stats.radius, 0.02 * math.sqrt(ALPHA), rtol=1e-6)


def test_a_pixel_photons_have_reached_is_never_refitted():
    """After a resume (a checkpoint keeps N, R and tau, not which pixels
    were fitted), a pixel with photons keeps its radius: resetting it would
    change its estimate."""
    rng = np.random.default_rng(6)
    hits = _floor_hit_points()
    stats = _stats(hits)
    stats.apply_photons(_floor_deposits(rng, 400_000), 400_000, MATTE)
    before = stats.radius.copy()
    stats.fitted[:] = False                          # as resumed from a checkpoint
    stats.fit_radii(hits.pixel, pilot_radius(hits), np.full(len(hits), 1e-4))
    stats.apply_photons(_floor_deposits(rng, 400_000), 400_000, MATTE)
    reached = stats.photon_count > 0
    assert reached.mean() > 0.99
    assert np.all(stats.radius[reached] <= before[reached])      # only shrunk by eq. 2, never reset
