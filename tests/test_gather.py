"""Both gathers against a brute-force reference that tests every (hit point,
photon) pair: the grid gather must equal it, the stochastic hash (HJ10)
must equal it where no photon is lost to a collision and agree with it in
expectation (over selection seeds) where many are."""
import math

import numba
import numpy as np
import pytest

from dosppm_core.jobs import HitPoints, PhotonDeposits
from dosppm_core.kernels.bsdf import eval_bsdf
from dosppm_core.scene.model import Material, MaterialTable
from dosppm_core.sppm.grid import gather_grid, grid_layout
from dosppm_core.sppm.hash import build_photon_hash, gather_hash, hash_layout, hash_statistics
from dosppm_core.sppm import statistics as sppm_statistics
from dosppm_core.sppm.statistics import PixelStatistics, reorder_deposits, reorder_parts

MATERIALS = MaterialTable.from_materials([
    Material("matte", reflectance=(0.8, 0.5, 0.3)),
    Material("satin", kind="glossy", reflectance=(0.6, 0.7, 0.9), roughness=0.3),
    Material("polish", kind="glossy", reflectance=(0.9, 0.9, 0.6), roughness=0.08),
])
SEEDS = 200
Z_MAX = 5.0     # allowed |mean - exact| in standard errors, per hit point and channel
EXACT = dict(resolution=(512, 512, 512), table_size=1 << 27)   # one slot per cell


# -- inputs ----------------------------------------------------------------------
def _unit(v):
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def _hemisphere(rng, normal, min_cos=0.05):
    """Random unit directions on the side of each `normal`."""
    d = _unit(rng.normal(size=normal.shape))
    d = np.where(np.sum(d * normal, -1, keepdims=True) < 0, -d, d)
    return _unit(d + min_cos * normal)


def _deposits(rng, pos, normal):
    pos, normal = np.asarray(pos, float), np.broadcast_to(np.asarray(normal, float), np.shape(pos))
    return PhotonDeposits(position=pos.astype(np.float32),
                          incoming=_hemisphere(rng, normal).astype(np.float32),
                          flux=rng.uniform(0.1, 1.0, (len(pos), 3)).astype(np.float32))


def _hit_points(rng, pos, normal):
    pos, normal = np.asarray(pos, float), np.broadcast_to(np.asarray(normal, float), np.shape(pos))
    n = len(pos)
    return HitPoints(position=pos.astype(np.float32), normal=normal.astype(np.float32),
                     outgoing=_hemisphere(rng, normal).astype(np.float32),
                     weight=rng.uniform(0.2, 1.0, (n, 3)).astype(np.float32),
                     material=rng.integers(0, 3, n).astype(np.int32),
                     pixel=np.arange(n, dtype=np.int32))


def _case(seed=2, free=40, plane=70, photons_per_surface=150):
    """A floor (z = 0, facing +z), the front of a thin wall (x = 0.5,
    facing -x) with photons right behind it (x = 0.504, facing +x: the next
    cell layer of the finest hash grid), and free-floating points with
    random normals, all in the unit cube; two photons lie far outside.

    Radii: median exactly 1/16 and maximum 1/2, with the hit points' box
    from 0 to 1, so the grid's cells are 1/8 wide from -1/2 and the hash's
    are dyadic too: photons at multiples of 1/8 lie exactly on cell
    boundaries of both. Six photons lie exactly 1/16 from a hit point of
    radius 1/16, on a boundary of the finest hash grid. Radii up to 1/2
    span many cells.
    Returns (photons, hit points, radii, which photons are behind the wall,
    which hit points are on the wall)."""
    rng = np.random.default_rng(seed)
    u = lambda n: rng.uniform(0, 1, n)  # noqa: E731
    # Hit points: floor, wall front, free, the two box corners, and a row on
    # dyadic floor points that get a photon exactly at their radius.
    k = np.arange(1, 7)
    exact_hp = np.c_[k / 8, k / 16, np.zeros(6)]
    hp_parts = [
        _hit_points(rng, np.c_[u(plane), u(plane), np.zeros(plane)], (0, 0, 1)),
        _hit_points(rng, np.c_[np.full(plane, 0.5), u(plane), u(plane)], (-1, 0, 0)),
        _hit_points(rng, rng.uniform(0, 1, (free, 3)), _unit(rng.normal(size=(free, 3)))),
        _hit_points(rng, [(0, 0, 0), (1, 1, 1)], [(0, 0, 1), (0, 0, 1)]),
        _hit_points(rng, exact_hp, (0, 0, 1)),
    ]
    hp = HitPoints.concat(hp_parts)
    n = len(hp)
    r = np.where(rng.random(n) < 0.45, rng.uniform(0.01, 0.06, n), 0.0625)
    big = rng.random(n) < 0.35
    r[big] = rng.uniform(0.07, 0.4, big.sum())
    r[-6:] = 0.0625
    r[rng.integers(0, 2 * plane)] = 0.5
    assert np.median(r) == 0.0625 and r.max() == 0.5
    hp.pixel[:] = np.arange(n)
    # Photons: random ones on each surface, a lattice on the floor's cell
    # boundaries, and one at exactly the radius of each dyadic hit point.
    m = photons_per_surface
    wall_y, wall_z = u(m), u(m)
    lattice = rng.choice(81, 40, replace=False)
    ph_parts = [
        _deposits(rng, np.c_[u(m), u(m), np.zeros(m)], (0, 0, 1)),
        _deposits(rng, np.c_[np.full(m, 0.5), wall_y, wall_z], (-1, 0, 0)),
        _deposits(rng, rng.uniform(-0.2, 1.2, (m, 3)), _unit(rng.normal(size=(m, 3)))),
        _deposits(rng, np.c_[lattice // 9 / 8, lattice % 9 / 8, np.zeros(40)], (0, 0, 1)),
        _deposits(rng, exact_hp + [1 / 16, 0, 0], (0, 0, 1)),
        _deposits(rng, np.c_[np.full(m, 0.504), wall_y, wall_z], (1, 0, 0)),   # behind the wall
        _deposits(rng, [(5.0, 0.5, 0.5), (-3.0, 0.2, 0.1)], (0, 0, 1)),          # outside the box
    ]
    ph = PhotonDeposits.concat(ph_parts)
    behind = np.zeros(len(ph), bool)
    behind[-m - 2:-2] = True
    on_wall = np.zeros(n, bool)
    on_wall[plane:2 * plane] = True
    return ph, hp, r, behind, on_wall


# -- the reference --------------------------------------------------------------------
def brute_force_pairs(ph, hp, radius, materials=MATERIALS):
    """Every (hit point, photon) pair that counts, with the gathers' float32
    distance and hemisphere tests, and its BRDF-weighted flux. The BRDF is the
    scalar kernel (checked on its own in
    `test_reference_brdf_matches_float64_formulas`)."""
    d = ph.position[None, :, :] - hp.position[:, None, :]                # float32
    d2 = d[..., 0] * d[..., 0] + d[..., 1] * d[..., 1] + d[..., 2] * d[..., 2]
    hn, wi = hp.normal[:, None, :], ph.incoming[None, :, :]
    cos_in = hn[..., 0] * wi[..., 0] + hn[..., 1] * wi[..., 1] + hn[..., 2] * wi[..., 2]
    ok = (d2.astype(np.float64) <= (radius * radius)[:, None]) & (cos_in > 0)
    hs, js = np.nonzero(ok)
    phi = np.zeros((len(hs), 3))
    for i, (h, j) in enumerate(zip(hs, js)):
        mat = hp.material[h]
        f = float(eval_bsdf(materials.kind[mat], np.float64(materials.roughness[mat]),
                            *hp.normal[h], *hp.outgoing[h], *ph.incoming[j]))
        if f > 0.0:
            phi[i] = [f * float(materials.reflectance[mat, k]) * float(hp.weight[h, k])
                      * float(ph.flux[j, k]) for k in range(3)]
    return hs, js, phi


def brute_force(ph, hp, radius):
    """(M, Phi) per hit point."""
    hs, _, phi_pairs = brute_force_pairs(ph, hp, radius)
    m = np.bincount(hs, minlength=len(hp)).astype(np.float64)
    phi = np.zeros((len(hp), 3))
    for i, h in enumerate(hs):      # in photon order, like a sequential gather
        phi[h] += phi_pairs[i]
    return m, phi


def hash_variance(ph, hp, radius, layout):
    """Exact variance of the hash's (M, Phi) per hit point. A slot s with
    c_s photons, of which the ones in range contribute g_p, adds
    c_s * g_kept; its variance is c_s * sum g_p^2 - (sum g_p)^2, and the
    slots are selected independently."""
    _, slots = layout.locate(ph.position)
    count = np.bincount(slots[slots >= 0])
    hs, js, phi_pairs = brute_force_pairs(ph, hp, radius)
    assert np.all(slots[js] >= 0)
    g = np.c_[np.ones(len(hs)), phi_pairs]                       # M and the 3 Phi channels
    groups, inverse = np.unique(np.c_[hs, slots[js]], axis=0, return_inverse=True)
    s1 = np.zeros((len(groups), 4))
    s2 = np.zeros((len(groups), 4))
    np.add.at(s1, inverse.ravel(), g)
    np.add.at(s2, inverse.ravel(), g * g)
    var_groups = count[groups[:, 1]][:, None] * s2 - s1 * s1
    var = np.zeros((len(hp), 4))
    np.add.at(var, groups[:, 0], np.maximum(var_groups, 0.0))
    return var[:, 0], var[:, 1:]


def _brdf_float64(kind, alpha, n, wo, wi):
    cos_o, cos_i = n @ wo, n @ wi
    if cos_o <= 0 or cos_i <= 0:
        return 0.0
    if kind == 0:
        return 1 / math.pi
    h = _unit(wo + wi)
    c2, a2 = (n @ h) ** 2, alpha * alpha
    dist = a2 / (math.pi * (c2 * (a2 - 1) + 1) ** 2)
    g1 = lambda c: 2 / (1 + math.sqrt(1 + a2 * (1 - c * c) / (c * c)))  # noqa: E731
    return dist * g1(cos_o) * g1(cos_i) / (4 * cos_o * cos_i)


def test_reference_brdf_matches_float64_formulas():
    rng = np.random.default_rng(3)
    n = np.array([0.0, 0.0, 1.0])
    for _ in range(200):
        wo, wi = _hemisphere(rng, np.tile(n, (2, 1)), 0.2).astype(np.float32)
        for kind, alpha in ((0, 0.3), (3, 0.3), (3, 0.08)):
            ours = float(eval_bsdf(np.int32(kind), np.float64(alpha), *n.astype(np.float32),
                                   *wo, *wi))
            # The kernel works partly in float32: sharp lobes amplify that.
            exact = _brdf_float64(kind, alpha, n, wo.astype(float), wi.astype(float))
            assert ours == pytest.approx(exact, rel=1e-4)


@pytest.fixture
def one_numba_thread():
    """The many-seed loops make thousands of tiny parallel launches; on a
    busy 2-core machine each may wait a scheduler slice for a sleeping
    worker (seconds in all). One numba thread keeps them fast, and the
    kernels still split their work in `threads` ranges."""
    saved = numba.get_num_threads()
    numba.set_num_threads(1)
    yield
    numba.set_num_threads(saved)


@pytest.fixture(scope="module")
def case():
    ph, hp, r, behind, on_wall = _case()
    return ph, hp, r, behind, on_wall, brute_force(ph, hp, r)


def test_case_covers_the_edge_cases(case):
    ph, hp, r, behind, on_wall, (m, _) = case
    # Photons behind the wall are within reach of wall hit points...
    d = np.linalg.norm(ph.position[behind][None] - hp.position[on_wall][:, None], axis=-1)
    assert (d <= r[on_wall][:, None]).sum() > 50
    # ...the dyadic hit points each have one photon at exactly their radius...
    at_radius = ph.take(np.arange(3 * 150 + 40, 3 * 150 + 46))       # the fifth part
    assert np.all(np.sum((at_radius.position - hp.position[-6:]) ** 2, axis=1) == r[-6:] ** 2)
    np.testing.assert_array_equal(brute_force(at_radius, hp.take(np.arange(len(hp) - 6, len(hp))),
                                              r[-6:])[0], 1.0)
    # ...and the largest radius spans many cells of both grids.
    lo, cell, _dims = grid_layout(hp.position, r)
    assert cell == 0.125 and np.all(lo == -0.5)
    fine = hash_layout(hp.position, r, **EXACT)
    assert np.all(fine.cell == 1 / 256) and np.all(fine.lo == -0.5)
    stats = hash_statistics(ph, hp, r, **EXACT)
    assert stats["cells_per_hit_point_max"] > 10_000


# -- grid: exact ----------------------------------------------------------------------
@pytest.mark.parametrize("threads", [1, 3])
def test_grid_equals_brute_force(case, threads):
    ph, hp, r, _, _, (m, phi) = case
    gm, gphi = gather_grid(ph, hp, r, MATERIALS, threads)
    np.testing.assert_array_equal(gm, m)
    np.testing.assert_allclose(gphi, phi, rtol=1e-9, atol=0)


def test_photons_behind_a_thin_wall_do_not_count(case):
    ph, hp, r, behind, on_wall, (m, phi) = case
    front = ph.take(np.nonzero(~behind)[0])
    m_front, phi_front = brute_force(front, hp, r)
    np.testing.assert_array_equal(m[on_wall], m_front[on_wall])
    np.testing.assert_array_equal(phi[on_wall], phi_front[on_wall])
    for gather, opts in ((gather_grid, {}), (gather_hash, EXACT)):
        gm, gphi = gather(ph, hp, r, MATERIALS, 2, **opts)
        gm_front, gphi_front = gather(front, hp, r, MATERIALS, 2, **opts)
        np.testing.assert_array_equal(gm[on_wall], gm_front[on_wall])
        # (the grid's per-thread photon ranges shift, so sums may reorder)
        np.testing.assert_allclose(gphi[on_wall], gphi_front[on_wall], rtol=1e-12, atol=0)


# -- hash: exact without collisions, unbiased with them --------------------------------
def test_hash_layout_gives_the_short_axis_the_small_resolution():
    pos = np.array([[0, 0, 0], [4, 1, 2]], np.float32)
    L = hash_layout(pos, np.array([0.1, 0.1]))
    dims = np.empty(3, np.int64)
    dims[L.axes] = L.dims
    assert tuple(dims) == (512, 128, 512)
    assert L.table_size == 1 << 24 and not L.identity
    np.testing.assert_allclose(L.cell[L.axes.argsort()] * dims, [4.2, 1.2, 2.2])


@pytest.mark.parametrize("threads", [1, 3])
def test_hash_without_collisions_equals_brute_force(case, threads):
    ph, hp, r, _, _, (m, phi) = case
    table = build_photon_hash(ph, hp.position, r, threads, **EXACT)
    assert table.layout.identity and table.photons_binned == len(ph) - 2
    assert table.photons_discarded == 0, "test input must have one photon per cell"
    hm, hphi = gather_hash(ph, hp, r, MATERIALS, threads, **EXACT, seed=threads)
    np.testing.assert_array_equal(hm, m)
    np.testing.assert_allclose(hphi, phi, rtol=1e-9, atol=0)


@pytest.mark.parametrize("opts", [dict(resolution=(8, 4, 8), table_size=61),
                                  dict(resolution=(8, 5, 13), table_size=7), EXACT])
def test_hash_records_match_their_slots(case, opts):
    """Every occupied cell has a record holding a photon of its own slot,
    the slot's photon count, and its entry if other cells share the slot."""
    ph, hp, r, *_ = case
    table = build_photon_hash(ph, hp.position, r, 2, **opts)
    L = table.layout
    cells, slots = L.locate(ph.position)
    bit = np.nonzero(np.unpackbits(table.bitmap.view(np.uint8), bitorder="little"))[0]
    words = (L.dims[2] + 63) // 64
    occupied = bit // 64 // words * L.dims[2] + bit // 64 % words * 64 + bit % 64
    np.testing.assert_array_equal(occupied, np.unique(cells[cells >= 0]))
    assert len(table.cell_count) == len(occupied)
    assert len(table.count) == len(np.unique(slots[slots >= 0]))
    for k, c in enumerate(occupied):
        slot = slots[cells == c][0]
        members = slots == slot
        assert slots[table.cell_photon[k]] == slot
        assert table.cell_count[k] == members.sum()
        assert (table.cell_shared[k] >= 0) == (len(np.unique(cells[members])) > 1)
    kept = table.cell_photon
    for name in ("position", "incoming", "flux"):
        np.testing.assert_array_equal(getattr(table, name), getattr(ph, name)[kept])


def test_hash_is_deterministic_and_independent_of_photon_order(case):
    ph, hp, r, *_ = case
    opts = dict(resolution=(8, 4, 8), table_size=61, seed=5)
    a = gather_hash(ph, hp, r, MATERIALS, 1, **opts)
    b = gather_hash(ph, hp, r, MATERIALS, 3, **opts)
    perm = np.random.default_rng(0).permutation(len(ph))
    c = gather_hash(ph.take(perm), hp, r, MATERIALS, 2, **opts)
    for x in (b, c):
        np.testing.assert_array_equal(x[0], a[0])
        np.testing.assert_array_equal(x[1], a[1])
    other = gather_hash(ph, hp, r, MATERIALS, 1, **dict(opts, seed=6))
    assert not np.array_equal(other[0], a[0])


def _assert_mean_agrees(samples, exact, variance, what):
    """Per element |mean - exact| <= Z_MAX standard errors of the mean (the
    exact variance over sqrt(samples)); and the squared z-scores average
    about 1, so the errors are as large as the variance says and no larger.
    Zero variance means every sample must be exact."""
    samples = np.asarray(samples)
    mean = samples.mean(axis=0)
    se = np.sqrt(variance / len(samples))
    err = np.abs(mean - exact)
    bad = err > Z_MAX * se + 1e-9 * np.abs(exact)
    assert not bad.any(), f"{what}: {bad.sum()} of {bad.size} outside {Z_MAX} SE"
    z2 = (err[se > 0] / se[se > 0]) ** 2
    if len(z2):
        limit = 1.0 + 6.0 * math.sqrt(2.0 / len(z2))
        assert z2.mean() < limit, f"{what}: mean z^2 {z2.mean():.2f} >= {limit:.2f}"


def test_hash_with_collisions_is_unbiased(case, one_numba_thread):
    """A coarse grid and a table smaller than the grid: most photons are
    lost, and cells share slots (so hit points reach some slots twice and
    must count them once). The mean over seeds must still be the exact
    gather, within the standard error computed from the exact variance."""
    ph, hp, r, _, _, (m, phi) = case
    opts = dict(resolution=(8, 4, 8), table_size=61)
    table = build_photon_hash(ph, hp.position, r, 2, **opts)
    assert table.discarded_fraction > 0.8 and table.multi.sum() > 20
    var_m, var_phi = hash_variance(ph, hp, r, table.layout)
    runs = [gather_hash(ph, hp, r, MATERIALS, 2, **opts, seed=s) for s in range(SEEDS)]
    _assert_mean_agrees([x[0] for x in runs], m, var_m, "M")
    _assert_mean_agrees([x[1] for x in runs], phi, var_phi, "Phi")


def test_hash_statistics_count_discarded_photons(case):
    ph, hp, r, *_ = case
    s = hash_statistics(ph, hp, r, resolution=(8, 4, 8), table_size=61)
    assert s["photons_binned"] == len(ph) - 2      # two photons lie far outside the box
    assert s["photons_discarded"] == s["photons_binned"] - s["slots_used"]
    assert s["slots_used"] <= 61
    assert s["discarded_fraction"] == pytest.approx(1 - s["slots_used"] / s["photons_binned"])
    assert hash_statistics(ph, hp, r, **EXACT)["discarded_fraction"] == 0.0


def test_gathers_take_the_reordered_columns_as_deposits(case):
    """The statistics update passes its photons as Morton-ordered columns
    (a GatherPhotons tuple, whose len() is 4): counts must come from the
    photons, and both gathers must give what they give for the deposits."""
    ph, hp, r, _, _, (m, phi) = case
    cols = reorder_deposits(ph, None)
    assert build_photon_hash(cols, hp.position, r, 2, **EXACT).photons == len(ph)
    hm, _ = gather_hash(cols, hp, r, MATERIALS, 2, **EXACT)
    np.testing.assert_array_equal(hm, m)
    gm, gphi = gather_grid(cols, hp, r, MATERIALS, 2)
    np.testing.assert_array_equal(gm, m)
    np.testing.assert_allclose(gphi, phi, rtol=1e-9, atol=0)


def test_reordering_parts_gives_the_rows_of_reordering_their_concatenation(case):
    """The server hands a batch over as the parts it arrived in; reordered
    from the parts, the gather reads exactly the rows it reads of the
    concatenation (order included, so the sums are bit for bit the same)."""
    ph = case[0]
    cuts = [0, 1, 7, 7, len(ph) // 2, len(ph)]
    parts = [ph.slice(a, b) for a, b in zip(cuts, cuts[1:])]
    box = np.stack([ph.position.min(0) - 0.1, ph.position.max(0) + 0.1]).astype(np.float64)
    whole, split = reorder_deposits(ph, box, threads=1), reorder_parts(parts, box)
    for name in ("position", "incoming", "flux"):
        np.testing.assert_array_equal(getattr(split, name), getattr(whole, name))
    assert not np.array_equal(whole.position, ph.position)      # it did reorder


# -- through the pixel statistics ------------------------------------------------------
def _pixel_setup(seed=11, width=8, height=6):
    """One hit point per pixel on a floor (mixed materials), photons on the
    floor and below it (facing down: they must not count)."""
    rng = np.random.default_rng(seed)
    gx, gy = np.meshgrid((np.arange(width) + 0.5) / width, (np.arange(height) + 0.5) / width)
    hp = _hit_points(rng, np.c_[gx.ravel(), gy.ravel(), np.zeros(gx.size)], (0, 0, 1))
    top = rng.uniform([-0.1, -0.1, 0], [1.1, 0.85, 0], (2000, 3))
    below = rng.uniform([-0.1, -0.1, -1e-3], [1.1, 0.85, -1e-3], (300, 3))
    deposits = PhotonDeposits.concat([_deposits(rng, top, (0, 0, 1)),
                                      _deposits(rng, below, (0, 0, -1))])
    return hp, deposits, (width, height)


def _render(hp, deposits, size, gather, **hash_options):
    stats = PixelStatistics(*size, radius=0.09)
    stats.replace_hit_points(hp, (np.zeros(0, np.int64), np.zeros((0, 3))))
    stats.apply_photons(deposits, 5000, MATERIALS, gather=gather, threads=2,
                        hash_options=hash_options or None)
    return stats.radiance(), stats.photon_count


@pytest.mark.parametrize("gather", ["grid", "hash"])
def test_a_batch_in_parts_is_the_same_update(gather):
    """A batch applied as a list of parts (the server's way) is the update
    of the whole batch at once: the same N and image."""
    hp, deposits, size = _pixel_setup()
    image, count = _render(hp, deposits, size, gather, seed=3)
    parts = [deposits.slice(a, min(a + 700, len(deposits))) for a in range(0, len(deposits), 700)]
    image_parts, count_parts = _render(hp, parts, size, gather, seed=3)
    np.testing.assert_allclose(count_parts, count, rtol=1e-12)
    np.testing.assert_allclose(image_parts, image, rtol=1e-9)


def test_a_batch_gathered_in_slices_is_the_same_update(monkeypatch):
    """A batch larger than GATHER_SLICE (a server's last) is gathered in
    slices and applied once: the grid's exact sums are the whole batch's.
    (The hash keeps a photon per slot, so its sliced estimate is another
    unbiased one, not the same.)"""
    hp, deposits, size = _pixel_setup()
    image, count = _render(hp, deposits, size, "grid")
    monkeypatch.setattr(sppm_statistics, "GATHER_SLICE", 1000)
    assert len(deposits) > 2 * 1000
    image_sliced, count_sliced = _render(hp, deposits, size, "grid")
    np.testing.assert_allclose(count_sliced, count, rtol=1e-12)
    np.testing.assert_allclose(image_sliced, image, rtol=1e-9)


def test_pixel_statistics_hash_and_grid_agree_in_expectation(one_numba_thread):
    hp, deposits, size = _pixel_setup()
    image, count = _render(hp, deposits, size, "grid")
    assert np.all(count > 0) and np.all(image > 0)
    floor_only = deposits.take(np.arange(2000))
    np.testing.assert_allclose(_render(hp, floor_only, size, "grid")[0], image, rtol=1e-12)
    # One batch from empty statistics is linear in (M, Phi): N = alpha M and
    # radiance = Phi / (emitted pi R0^2), so the mean image over seeds must
    # match the exact one, with the hash's variance scaled alike.
    radius = np.full(len(hp), 0.09)
    to_radiance = 1.0 / (5000 * math.pi * 0.09 ** 2)
    for opts, seeds in ((dict(resolution=(16, 4, 16), table_size=53), SEEDS),
                        (dict(), 20)):          # the paper's grid and 2**24 slots
        layout = hash_layout(hp.position, radius, **opts)
        var_m, var_phi = hash_variance(deposits, hp, radius, layout)
        runs = [_render(hp, deposits, size, "hash", seed=s, **opts) for s in range(seeds)]
        _assert_mean_agrees([x[0] for x in runs], image,
                            (var_phi * to_radiance ** 2).reshape(image.shape), f"radiance {opts}")
        _assert_mean_agrees([x[1] for x in runs], count, var_m * 0.7 ** 2, f"photon count N {opts}")
