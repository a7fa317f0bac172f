"""One statistics update (eqs. 1, 2 and 4 of Günther & Grosch §3.2) as
`PixelStatistics.apply_sums` runs it, in one compiled pass: it must equal
the equations written out in float64, pixel by pixel, bit for bit, over
pixels in any order, pixels that met no photon, and several updates."""
from __future__ import annotations

import numpy as np

from dosppm_core.sppm.statistics import PixelStatistics


def _by_the_equations(n, r, tau, pixel, m, phi, alpha):
    n, r, tau = n.copy(), r.copy(), tau.copy()
    for p, mi, ph in zip(pixel, m, phi):
        if mi <= 0:
            continue                                   # no photon: nothing changes
        n_new = n[p] + alpha * mi                      # eq. 1
        shrink = n_new / (n[p] + mi)                   # eq. 2, squared
        r[p] = r[p] * np.sqrt(shrink)
        tau[p] = (tau[p] + ph) * shrink                # eq. 4
        n[p] = n_new
    return n, r, tau


def test_an_update_is_eqs_1_2_and_4_for_every_pixel_that_met_photons():
    rng = np.random.default_rng(7)
    st = PixelStatistics(16, 8, radius=0.25, alpha=0.6)
    for _ in range(3):
        pixel = rng.permutation(128)[:100]              # scattered, some pixels left out
        m = rng.integers(0, 4, 100).astype(np.float64)  # a quarter met no photon
        phi = rng.random((100, 3)) * (m > 0)[:, None]
        want = _by_the_equations(st.photon_count, st.radius, st.tau, pixel, m, phi, st.alpha)
        st.apply_sums(pixel, m, phi, emitted=1000)
        for got, w in zip((st.photon_count, st.radius, st.tau), want):
            assert np.array_equal(got, w)
    assert st.photons_emitted == 3000
    untouched = np.setdiff1d(np.arange(128), pixel)
    assert (st.radius[untouched] <= 0.25).all()


def test_an_update_accepts_statistics_restored_as_views():
    # A checkpoint hands back arrays that may be views or other dtypes.
    st = PixelStatistics(4, 4, radius=1.0)
    st.tau = np.asfortranarray(st.tau)
    st.photon_count = st.photon_count.astype(np.float32)
    st.apply_sums(np.array([3]), np.array([2.0]), np.array([[1.0, 2.0, 3.0]]), emitted=10)
    assert st.photon_count[3] == np.float64(0.7 * 2)
    assert np.allclose(st.tau[3], np.array([1.0, 2.0, 3.0]) * 0.7)


def test_add_rows_is_numpys_add_at_distinct_rows():
    # The server sums tracers' sparse sums and light with it.
    from dosppm_core.sppm.statistics import add_rows
    rng = np.random.default_rng(3)
    for shape in ((50,), (50, 3)):
        out, want = rng.random(shape), None
        want = out.copy()
        rows = np.sort(rng.choice(50, 20, replace=False))
        vals = rng.random((20, *shape[1:]))
        want[rows] += vals
        add_rows(out, rows, vals)
        assert np.array_equal(out, want)
        add_rows(out, rows[:0], vals[:0])           # a tracer whose deposits reached no hit point
        assert np.array_equal(out, want)
