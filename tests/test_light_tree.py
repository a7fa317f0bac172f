"""The light tree (kernels/light_tree.py): at any point and normal, its
probabilities over the lights sum to 1, sampling draws each light as
often as its probability says (chi-square), and every light that can
light the point keeps a positive probability (the bounds are
conservative, so the estimator stays unbiased)."""
from __future__ import annotations

import math

import numpy as np
import pytest

from dosppm_core.kernels.light_tree import build_light_tree, sample_tree, tree_pmf
from dosppm_core.scene.model import LIGHT_POINT, LIGHT_SPOT, light_table


def _mixed_lights(rng, n_tri=300):
    """Triangles facing every way, point lights, and spots, over a 20 m box."""
    c = rng.uniform(-10, 10, (n_tri, 3))
    e1, e2 = rng.normal(0, 0.3, (n_tri, 3)), rng.normal(0, 0.3, (n_tri, 3))
    delta = []
    for _ in range(20):
        delta.append((LIGHT_POINT, rng.uniform(-10, 10, 3), np.zeros(3), rng.uniform(0.5, 3, 3), np.zeros(4)))
    for _ in range(20):
        axis = rng.normal(size=3)
        axis /= np.linalg.norm(axis)
        cutoff, beam = 0.7, 0.4
        delta.append((LIGHT_SPOT, rng.uniform(-10, 10, 3), axis, rng.uniform(0.5, 3, 3),
                      np.array([math.cos(cutoff), math.cos(beam), cutoff, beam])))
    return light_table(c, c + e1, c + e2, rng.uniform(0.1, 5, (n_tri, 3)), delta)


def _points(rng, k):
    p = rng.uniform(-12, 12, (k, 3))
    n = rng.normal(size=(k, 3))
    return p, n / np.linalg.norm(n, axis=1, keepdims=True)


@pytest.fixture(scope="module")
def lights():
    L = _mixed_lights(np.random.default_rng(3))
    return L, tuple(build_light_tree(L))


def _failure_mass(tree, x, nx, draws=4000, seed=0):
    """How often sampling at x finds no light (a node whose children both
    bound zero: none of its lights can light x)."""
    u = np.random.default_rng(seed).random(draws)
    return np.mean([sample_tree(tree, *x, *nx, ui)[0] < 0 for ui in u])


def test_probabilities_sum_to_one(lights):
    """With the mass of the walks that end at a node whose lights cannot
    light the point (sampling returns no light there): that mass is the
    sampler's own failure rate, and the rest is spread over the lights."""
    L, tree = lights
    p, n = _points(np.random.default_rng(4), 40)
    for k, (x, nx) in enumerate(zip(p, n)):
        pm = np.array([tree_pmf(tree, li, *x, *nx) for li in range(len(L.kind))])
        assert pm.min() >= 0.0
        assert pm.sum() <= 1.0 + 1e-9
        assert pm.sum() + _failure_mass(tree, x, nx, seed=k) == pytest.approx(1.0, abs=0.03)


def test_sampled_frequencies_match_the_probabilities(lights):
    """Chi-square over the lights drawn at one point (the ones with expected
    count >= 5, the rest pooled); the critical value at p = 1e-4 by the
    Wilson-Hilferty approximation."""
    L, tree = lights
    rng = np.random.default_rng(5)
    x, nx = np.array([1.0, -2.0, 0.5]), np.array([0.0, 0.0, 1.0])
    pm = np.array([tree_pmf(tree, li, *x, *nx) for li in range(len(L.kind))])
    draws = 200_000
    counts = np.zeros(len(pm) + 1)      # the last: no light found
    for u in rng.random(draws):
        li, q = sample_tree(tree, *x, *nx, u)
        if li >= 0:
            assert q == pytest.approx(pm[li], rel=1e-9)     # the pmf it returns is the one evaluated
        counts[li] += 1
    expected = draws * np.r_[pm, max(0.0, 1.0 - pm.sum())]
    big = expected >= 5
    obs = np.r_[counts[big], counts[~big].sum()]
    exp = np.r_[expected[big], expected[~big].sum()]
    keep = exp > 0
    chi2 = float(((obs[keep] - exp[keep]) ** 2 / exp[keep]).sum())
    k = int(keep.sum()) - 1
    z = 3.719                       # the normal quantile at 1 - 1e-4
    critical = k * (1 - 2 / (9 * k) + z * math.sqrt(2 / (9 * k))) ** 3
    assert big.sum() > 50           # a real spread of lights, not one
    assert chi2 < critical, (chi2, critical, k)


def test_every_light_that_can_light_a_point_keeps_a_positive_probability(lights):
    """Point lights above the surface, spots whose cone reaches the point,
    and triangles with a corner above the surface and the point in front
    of them (a corner's contribution is positive, so by continuity some of
    the triangle's is)."""
    L, tree = lights
    p, n = _points(np.random.default_rng(6), 60)
    checked = 0
    for x, nx in zip(p, n):
        for li in range(len(L.kind)):
            if L.kind[li] == LIGHT_POINT or L.kind[li] == LIGHT_SPOT:
                d = L.p0[li] - x
                dist = np.linalg.norm(d)
                lit = d @ nx > 0
                if L.kind[li] == LIGHT_SPOT:
                    lit = lit and -(d / dist) @ L.p1[li] > L.cone[li, 0]
            else:
                tri = np.stack([L.p0[li], L.p1[li], L.p2[li]])
                normal = np.cross(tri[1] - tri[0], tri[2] - tri[0])
                lit = bool(((tri - x) @ nx > 1e-6).any() and (x - tri[0]) @ normal > 1e-6)
            if lit:
                checked += 1
                assert tree_pmf(tree, li, *x, *nx) > 0.0, (li, x, nx)
    assert checked > 1000


def test_lights_without_power_are_left_out():
    L = light_table(np.zeros((2, 3)), np.array([[1.0, 0, 0], [1, 0, 0]]), np.array([[0, 1.0, 0], [0, 1, 0]]),
                    np.array([[1.0, 1, 1], [0, 0, 0]]))
    t = build_light_tree(L)
    assert list(t.leaf_of) == [0, -1]
    above, facing_down = (0.2, 0.2, 1.0), (0, 0, -1.0)
    assert tree_pmf(tuple(t), 1, *above, *facing_down) == 0.0
    assert tree_pmf(tuple(t), 0, *above, *facing_down) == 1.0
    # Behind the one-sided light (it emits toward +z): nothing can light there.
    assert sample_tree(tuple(t), 0.2, 0.2, -1.0, 0, 0, 1.0, 0.5) == (-1, 0.0)
