"""Pixel statistics of SPPM, exactly as eqs. 1-5 of Günther & Grosch §3.2.

Per pixel: the accumulated photon count N, the search radius R, the
BRDF-weighted flux tau, and the emission seen directly along eye paths.
Photon deposits are applied in batches (server batching, §4.3) to the hit
points of the latest complete eye iteration; photons of any emission round
are treated alike (§3.3). All statistics are float64: float32 would lose
photons to rounding after ~1e8 additions.

The update's kernels (here and in the gathers) release the GIL (nogil), so
the distributed server's message loop keeps answering while a statistics
update runs on another thread (§4.3 server batching).
"""
from __future__ import annotations

import math
from concurrent.futures import ThreadPoolExecutor
from typing import NamedTuple

import numba as nb
import numpy as np

from dosppm_core.jobs import HitPoints, PhotonDeposits
from dosppm_core.scene.model import Scene
from dosppm_core.sppm.grid import build_hit_point_grid, gather_grid, reach_box
from dosppm_core.sppm.hash import gather_hash

GATHERS = ("grid", "hash")
# One helper thread for the part of an update that overlaps the photon sort.
_PREP = ThreadPoolExecutor(1, thread_name_prefix="dosppm-gather-prep")


@nb.njit(cache=True, nogil=True)
def _spread(q):
    """The 10 low bits of q spread to every third bit."""
    x = np.uint32(q)
    x = (x | (x << np.uint32(16))) & np.uint32(0x030000FF)
    x = (x | (x << np.uint32(8))) & np.uint32(0x0300F00F)
    x = (x | (x << np.uint32(4))) & np.uint32(0x030C30C3)
    return (x | (x << np.uint32(2))) & np.uint32(0x09249249)


@nb.njit(cache=True, nogil=True)
def _morton_code(x, y, z, lo, scale, shift):
    """The Morton code of point (x, y, z) quantised to 1024 >> shift steps
    per axis over the box at `lo` (tuples, not arrays: numba reference-
    counts the arrays of a call, which in a loop over 1M points costs more
    than the code)."""
    lo0, lo1, lo2 = lo
    s0, s1, s2 = scale
    qx = min(max(int((x - lo0) * s0), 0), 1023) >> shift
    qy = min(max(int((y - lo1) * s1), 0), 1023) >> shift
    qz = min(max(int((z - lo2) * s2), 0), 1023) >> shift
    return _spread(qx) | (_spread(qy) << np.uint32(1)) | (_spread(qz) << np.uint32(2))


@nb.njit(cache=True, nogil=True, parallel=True)
def morton_packed(pos, lo, scale):
    """Per point, its 30-bit Morton code (positions quantised to 1024^3
    over a box) in the high 32 bits and its row in the low 32."""
    n = pos.shape[0]
    out = np.empty(n, np.uint64)
    for i in nb.prange(n):
        code = _morton_code(pos[i, 0], pos[i, 1], pos[i, 2], lo, scale, 0)
        out[i] = (np.uint64(code) << np.uint64(32)) | np.uint64(i)
    return out


@nb.njit(cache=True, nogil=True, parallel=True)
def _bucket_columns(pos, inc, flux, lo, scale, bits, threads, code, out):
    """The gather's columns, counting-sorted into 2^(3 bits) buckets along
    a Morton curve: a histogram and one scatter per thread over its own
    contiguous part of the rows, so the order is stable and the same for
    any thread timing. Into `out` (n, 9): position, incoming, flux; `code`
    (n,) int32 is scratch (both numpy's: see grid.build_grid)."""
    n = pos.shape[0]
    where = np.zeros((threads, 1 << (3 * bits)), np.int64)
    for t in nb.prange(threads):
        for i in range(n * t // threads, n * (t + 1) // threads):
            code[i] = _morton_code(pos[i, 0], pos[i, 1], pos[i, 2], lo, scale, 10 - bits)
            where[t, code[i]] += 1
    run = 0
    for b in range(where.shape[1]):       # bucket-major, then thread: stable
        for t in range(threads):
            run, where[t, b] = run + where[t, b], run
    for t in nb.prange(threads):
        for i in range(n * t // threads, n * (t + 1) // threads):
            d = where[t, code[i]]
            where[t, code[i]] = d + 1
            for k in range(3):
                out[d, k] = pos[i, k]
                out[d, 3 + k] = inc[i, k]
                out[d, 6 + k] = flux[i, k]


def gather_slices(parts: list):
    """The deposits of `parts` in slices of about GATHER_SLICE rows, each a
    list of parts (a large part cut into views): the gather's reordered
    copy (36 bytes a deposit) is a slice's, whatever the batch."""
    group, rows = [], 0
    for part in parts:
        for start in range(0, len(part), GATHER_SLICE):
            piece = part.slice(start, min(len(part), start + GATHER_SLICE))
            group.append(piece)
            rows += len(piece)
            if rows >= GATHER_SLICE:
                yield group
                group, rows = [], 0
    if group:
        yield group


@nb.njit(cache=True, nogil=True)
def _bucket_count(pos, lo, scale, bits, code, counts):
    """`_bucket_columns`'s histogram, for one part of a batch."""
    for i in range(pos.shape[0]):
        code[i] = _morton_code(pos[i, 0], pos[i, 1], pos[i, 2], lo, scale, 10 - bits)
        counts[code[i]] += 1


@nb.njit(cache=True, nogil=True)
def _bucket_scatter(pos, inc, flux, code, where, out):
    """`_bucket_columns`'s scatter, for one part, from where the parts
    before it left each bucket."""
    for i in range(pos.shape[0]):
        d = where[code[i]]
        where[code[i]] = d + 1
        for k in range(3):
            out[d, k] = pos[i, k]
            out[d, 3 + k] = inc[i, k]
            out[d, 6 + k] = flux[i, k]


def reorder_parts(parts: list, box: np.ndarray) -> "GatherPhotons":
    """`reorder_deposits` (one thread) of the parts' concatenation, read
    from the parts themselves: the same rows in the same order, without
    the concatenated copy (the server hands its batches over as parts)."""
    scale = 1023.999 / np.maximum(box[1] - box[0], 1e-30)
    lo, scale = tuple(map(float, box[0])), tuple(map(float, scale))
    counts = np.zeros(1 << (3 * BUCKET_BITS), np.int64)
    codes = []
    for p in parts:
        codes.append(np.empty(len(p), np.int32))
        _bucket_count(p.position, lo, scale, BUCKET_BITS, codes[-1], counts)
    where = np.zeros_like(counts)
    np.cumsum(counts[:-1], out=where[1:])
    out = np.empty((int(counts.sum()), 9), np.float32)
    for p, code in zip(parts, codes):
        _bucket_scatter(p.position, p.incoming, p.flux, code, where, out)
    return GatherPhotons(out[:, 0:3], out[:, 3:6], out[:, 6:9])


class GatherPhotons(NamedTuple):
    """What a gather reads of photon deposits (PhotonDeposits has the same
    attributes, so either can be gathered): a photon counts by the hit
    point's side, as in pbrt-v4, so neither carries a surface normal."""
    position: np.ndarray
    incoming: np.ndarray
    flux: np.ndarray


# Deposits gathered at once (`gather_slices`): a batch of 1M is one slice,
# a larger one (a server's last, or merged, update) is cut, so the
# reordered copy stays 36 MiB. Smaller slices cost time: at 256k, each
# slice's per-hit-point sums made an update 24% slower at 60k hit points
# and 63% slower at 640k (`dosppm bench`, medians of 5).
GATHER_SLICE = 1 << 20
BUCKET_BITS = 5   # 32^3 buckets: of the order of the grid's cells, so a bucket's cells stay in cache


def reorder_deposits(deposits: PhotonDeposits, box: np.ndarray | None,
                     threads: int = 2) -> GatherPhotons:
    """The gather's columns of `deposits`, bucketed along a Morton curve
    over `box` (the gather's box): the spatial reordering of the Photon
    Pipeline paper, by a counting sort (2x faster here than sorting full
    Morton keys, and the gather runs as fast)."""
    pos = deposits.position
    if box is None:
        box = np.stack([pos.min(0), pos.max(0)]).astype(np.float64)
    scale = 1023.999 / np.maximum(box[1] - box[0], 1e-30)
    out = np.empty((len(pos), 9), np.float32)   # one interleaved row per deposit
    _bucket_columns(pos, deposits.incoming, deposits.flux, tuple(map(float, box[0])),
                    tuple(map(float, scale)), BUCKET_BITS, max(1, threads),
                    np.empty(len(pos), np.int32), out)
    return GatherPhotons(out[:, 0:3], out[:, 3:6], out[:, 6:9])


@nb.njit(cache=True, nogil=True)
def _update_pixels(pixel, m, phi, alpha, photon_count, radius, tau):
    """Eqs. 1, 2 and 4 for the hit points that met photons (m > 0), in
    place: one pass, where the same arithmetic in numpy fancy indexing took
    11 ms an update over 65k scattered pixels, a fifth of a server's CPU
    gathering at the tracers (issue 32). A pixel has one hit point."""
    for i in range(pixel.shape[0]):
        if not m[i] > 0:
            continue
        p = pixel[i]
        n_old = photon_count[p]
        n_new = n_old + alpha * m[i]                                     # eq. 1
        shrink = n_new / (n_old + m[i])                                  # (R_{i+1}/R_i)^2, eq. 2
        radius[p] *= math.sqrt(shrink)
        for k in range(3):
            tau[p, k] = (tau[p, k] + phi[i, k]) * shrink                 # eq. 4
        photon_count[p] = n_new


@nb.njit(cache=True, nogil=True)
def _add_rows(out, rows, values):
    for i in range(rows.shape[0]):
        r = rows[i]
        for k in range(values.shape[1]):
            out[r, k] += values[i, k]


def add_rows(out: np.ndarray, rows: np.ndarray, values: np.ndarray) -> None:
    """out[rows] += values, in place, for distinct rows (a tracer's sums
    or light per hit point or pixel, summed at the server): one compiled
    pass, 10x numpy's gather-add-scatter over 65k rows. `out` float64 and
    1-D or (n, k)."""
    flat = out if out.ndim == 2 else out[:, None]      # a view either way, empty or not
    vals = np.ascontiguousarray(values, np.float64).reshape(len(rows), flat.shape[1])
    _add_rows(flat, np.ascontiguousarray(rows, np.int64), vals)


def _morton_sorted(pos: np.ndarray, box: np.ndarray | None) -> np.ndarray:
    """(Morton key << 32 | row) of every point, sorted. Sorting one packed
    uint64 is 3-5x faster than a stable argsort here, and as deterministic."""
    if box is None:
        box = np.stack([pos.min(0), pos.max(0)]).astype(np.float64)
    ext = np.maximum(box[1] - box[0], 1e-30)
    packed = morton_packed(pos, tuple(map(float, box[0])), tuple(map(float, 1023.999 / ext)))
    packed.sort()
    return packed


def spatial_order(pos: np.ndarray, box: np.ndarray | None = None) -> np.ndarray:
    """Permutation sorting points along a Morton curve. Gathering in this
    order keeps the grid cells and hit points a thread touches in cache
    (the reordering of the Photon Pipeline paper; 5-10x on this machine)."""
    if len(pos) == 0:
        return np.zeros(0, np.int64)
    return (_morton_sorted(pos, box) & np.uint64(0xFFFFFFFF)).astype(np.int64)


# The initial radius, fitted per hit point to the photons that reach it
# (Hachisuka et al.'s k nearest photons, from one pilot gather): a disc
# expected to hold RADIUS_SHARE times a hit point's fair share of a batch
# (1 / hit points), so bright and dark regions start at the same relative
# noise whatever the scene's scale, its lights' power or the image's size.
# 8 was best of 4, 8 and 16 on both Sponza (320x240) and the Cornell box
# (128x128), where one count of photons per million (120) fitted Sponza but
# left the box 1.6x noisier (docs/accuracy.md, "The initial radius").
RADIUS_SHARE = 8.0
PILOT_DIAGONAL = 1.0 / 50.0   # pilot radius, as a fraction of the hit points' box diagonal
PILOT_DEPOSITS = 100_000      # deposits the pilot gather reads at most
MIN_RADIUS_PIXELS = 1.0       # no radius below one pixel footprint: the pixel filter blurs as much


def pixel_footprint(scene: Scene, hits: HitPoints, pixels_across: float = MIN_RADIUS_PIXELS) -> np.ndarray:
    """`pixels_across` pixel footprints at each hit point's distance from
    the camera, kept within [1e-5, 1/20] of the scene's size."""
    frame = scene.camera.frame()
    diag = scene.diagonal()
    dist = np.linalg.norm(hits.position.astype(np.float64) - frame[0], axis=1)
    # An orthographic pixel has the same width at every distance.
    spread = np.ones_like(dist) if frame[6, 0] > 0 else dist
    footprint = 2.0 * frame[4, 0] * spread / int(scene.camera.width)
    return np.clip(pixels_across * footprint, 1e-5 * diag, diag / 20.0)


def pilot_radius(hits: HitPoints) -> float:
    """The radius a pixel starts at before its first photons: a fixed
    fraction of the hit points' extent (the view, not the whole scene)."""
    if len(hits) == 0:
        return 1.0
    p = hits.position.astype(np.float64)
    diag = float(np.linalg.norm(p.max(0) - p.min(0)))
    return max(diag * PILOT_DIAGONAL, 1e-6)


def subsample(deposits: PhotonDeposits | list, most: int, total: int | None = None) -> GatherPhotons:
    """About `most` of the deposits (a PhotonDeposits or a list of parts),
    chosen by a hash of their position bits: the same deposits whatever
    order a batch arrived in, so a pilot gather (and the radii it fits)
    depends on the batch alone (a render's ledger re-traces the batch in
    another order, services/ledger.py). Parts are read where they are: the
    batch is never copied whole. `total`: the whole batch's deposit count
    when `deposits` are one tracer's share of it; each deposit is chosen by
    its own hash and the cut, so the tracers' choices add up to the whole
    batch's (less the fallback below, which needs the whole batch)."""
    parts = deposits if isinstance(deposits, list) else [deposits]
    n = sum(len(p) for p in parts) if total is None else int(total)
    if n > most:
        cut = np.uint64(most / n * 2.0 ** 32)
        chosen = PhotonDeposits.concat([p.take(np.flatnonzero(_position_hash(p.position) < cut)) for p in parts])
        if len(chosen) == 0 and total is None:   # all hashed alike (a batch of one repeated position)
            chosen = PhotonDeposits.concat([p.slice(0, min(len(p), most)) for p in parts]).slice(0, most)
    else:
        chosen = PhotonDeposits.concat(parts)
    return GatherPhotons(chosen.position, chosen.incoming, chosen.flux)


def _position_hash(position: np.ndarray) -> np.ndarray:
    bits = np.ascontiguousarray(position, np.float32).view(np.uint32).astype(np.uint64)
    return (bits[:, 0] * 0x9E3779B1 ^ bits[:, 1] * 0x85EBCA77 ^ bits[:, 2] * 0xC2B2AE3D) & 0xFFFFFFFF


def gather_sums(deposits: PhotonDeposits | list, hp: HitPoints, radius: np.ndarray, materials,
                gather: str = "grid", threads: int = 2, reorder: bool = True,
                hash_options: dict | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Per hit point (M, Phi) of a batch's deposits (or any part of it) at
    the hit points' radii `radius`: summed over slices of the batch, so the
    temporaries are a slice's size. Sums of disjoint parts add up to the
    whole's (up to float64 summation order), which is what lets tracers
    gather their own deposits and the server add their sums."""
    parts = deposits if isinstance(deposits, list) else [deposits]
    if len(hp) == 0 or not any(len(p) for p in parts):
        return np.zeros(len(hp)), np.zeros((len(hp), 3))
    # Registering the hit points in the grid and sorting the photons are
    # both mostly serial: do them at once, on two cores.
    grid = _PREP.submit(build_hit_point_grid, hp, radius, materials) if gather == "grid" else None
    box = reach_box(hp.position, radius)
    m = phi = 0
    for group in gather_slices(parts):
        piece = reorder_parts(group, box) if reorder else PhotonDeposits.concat(group)
        if grid is not None:
            dm, dphi = gather_grid(piece, hp, radius, materials, threads, grid.result())
        else:
            dm, dphi = gather_hash(piece, hp, radius, materials, threads, **(hash_options or {}))
        m, phi = m + dm, phi + dphi
    return m, phi


def pilot_sums(deposits: PhotonDeposits | list, hpf: HitPoints, r_pilot: np.ndarray, materials,
               threads: int, most: int, total: int | None = None) -> tuple[np.ndarray, int]:
    """The pilot gather of `PixelStatistics.fit_from_pilot`: per hit point of
    `hpf`, the subsampled deposits within its pilot radius, and how many
    were subsampled. Both add up over tracers holding parts of a batch of
    `total` deposits."""
    pilot = subsample(deposits, most, total)
    m, _ = gather_grid(pilot, hpf, r_pilot, materials, threads)
    return m, len(pilot.position)


class PixelStatistics:
    """N, R, tau and directly seen emission per pixel (eqs. 1-5)."""

    def __init__(self, width: int, height: int, radius: float | None, alpha: float = 0.7):
        """`radius` None: each pixel's radius is fitted to the photon
        density at its hit point (`fit_radii`, then the pilot gather of
        the first batch that reaches it); else every pixel starts at it."""
        if not (0.0 < alpha < 1.0):
            raise ValueError(f"alpha must lie in (0, 1), got {alpha}")
        n = width * height
        self.width, self.height, self.alpha = width, height, alpha
        self.fit = radius is None
        self.fitted = np.zeros(n, bool)           # the pilot gather has set its radius
        self.photon_count = np.zeros(n)           # N_i
        self.radius = np.full(n, np.nan if radius is None else float(radius))  # R_i
        self.min_radius = np.zeros(n)             # per pixel: one pixel footprint
        self.tau = np.zeros((n, 3))               # tau_i
        self.emission = np.zeros((n, 3))          # sum over eye iterations
        self.eye_iterations = 0
        self.photons_emitted = 0                  # N_e
        self.hit_points = HitPoints.empty()

    @property
    def has_radius(self) -> bool:
        return not np.isnan(self.radius[0])

    def set_initial_radius(self, radius: float) -> None:
        if not radius > 0:
            raise ValueError(f"initial radius must be > 0, got {radius}")
        self.radius[:] = radius

    def fit_radii(self, pixels: np.ndarray, pilot: float, min_radii: np.ndarray) -> None:
        """Start every pixel not fitted yet (no photon has reached it: its
        radius has never shrunk and its tau is zero, so this changes no
        estimate) at the pilot radius; the next batch fits it to the photon
        density (`_fit_to_density`), once. Pixels without a hit point keep
        the pilot radius, so no radius is NaN."""
        if not self.has_radius:
            self.radius[:] = pilot
        fresh = self._unfitted(pixels)
        self.radius[pixels[fresh]] = np.maximum(pilot, min_radii[fresh])
        self.min_radius[pixels] = min_radii

    def _unfitted(self, pixels: np.ndarray) -> np.ndarray:
        """Which of `pixels` have neither been fitted nor reached by a photon
        (a checkpoint keeps no `fitted`: a resumed pixel with photons is
        never reset)."""
        return ~self.fitted[pixels] & (self.photon_count[pixels] == 0)

    def _fit_to_density(self, deposits, hp: HitPoints, materials, threads: int) -> None:
        """The radius of each pixel not fitted yet, from a pilot gather of (a
        subsample of) this batch at the pilot radius: the disc expected to
        hold RADIUS_SHARE / (hit points) of the deposits, kept between one
        pixel footprint and the pilot radius. A pixel the pilot finds no
        photon for (a light seen directly, a dark room) stays at the pilot
        radius and is tried again with the next batch, on a subsample as
        much smaller as such pixels are few (the Cornell box's lamp: 5%).
        In three steps (`pilot_request`, `pilot_sums`, `fit_from_pilot`) so
        that tracers holding parts of a batch can each run the middle one."""
        request = self.pilot_request()
        if request is None:
            return
        fresh, r_pilot, most = request
        m, chosen = pilot_sums(deposits, hp.take(fresh), r_pilot, materials, threads, most)
        self.fit_from_pilot(fresh, r_pilot, m, chosen)

    def pilot_request(self) -> tuple | None:
        """(rows of the hit points not fitted yet, their pilot radii, the
        subsample size) for the next batch's pilot gather; None if every
        hit point's pixel is fitted."""
        hp = self.hit_points
        if not self.fit or len(hp) == 0:
            return None
        fresh = np.flatnonzero(self._unfitted(hp.pixel))
        if len(fresh) == 0:
            return None
        few = min(1.0, max(0.1, 4.0 * len(fresh) / len(hp)))
        return fresh, self.radius[hp.pixel[fresh]], int(PILOT_DEPOSITS * few)

    def fit_from_pilot(self, fresh: np.ndarray, r_pilot: np.ndarray, m: np.ndarray, chosen: int) -> None:
        """Fit the radii of hit point rows `fresh` from the pilot gather's
        counts `m` of `chosen` subsampled deposits (summed over tracers)."""
        fit = self.fitted_radii(fresh, r_pilot, m, chosen)
        if fit is not None:
            self.commit_fit(*fit)

    def fitted_radii(self, fresh: np.ndarray, r_pilot: np.ndarray, m: np.ndarray, chosen: int) -> tuple | None:
        """(pixels, their fitted radii, which are fitted) of `fit_from_pilot`,
        not yet stored: a server gathering at its tracers stores them only
        with the batch they were fitted for (`commit_fit`), so a batch
        discarded after its pilot leaves the radii as they were."""
        if chosen <= 0:       # no deposit chosen: every pixel tries again next batch
            return None
        hp = self.hit_points
        pix = hp.pixel[fresh]
        share = m / chosen                              # of the deposits, within r_pilot
        target = RADIUS_SHARE / len(hp)                 # RADIUS_SHARE hit points' fair share
        with np.errstate(divide="ignore"):
            r0 = r_pilot * np.sqrt(target / share)
        return pix, np.clip(r0, self.min_radius[pix], r_pilot), m > 0

    def commit_fit(self, pix: np.ndarray, radius: np.ndarray, fitted: np.ndarray) -> None:
        self.radius[pix] = radius
        self.fitted[pix] = fitted

    # -- eye iterations -----------------------------------------------------
    def replace_hit_points(self, hits: HitPoints, seen_light: tuple) -> None:
        """Install a complete eye iteration: its hit points (sorted along a
        Morton curve for the gather) and the emission its paths saw."""
        self.hit_points = hits.take(spatial_order(hits.position))
        if seen_light is not None:      # None: its light comes on its own (`add_light`)
            self.add_emission(seen_light)

    def add_emission(self, seen_light: tuple) -> None:
        """A complete eye iteration's emission seen by its paths (direct
        light included), whether or not its hit points are installed: the
        image's emission term averages over every eye iteration."""
        pixel, rgb = seen_light
        for k in range(3):
            self.emission[:, k] += np.bincount(pixel, rgb[:, k], minlength=len(self.radius))
        self.eye_iterations += 1

    def add_light(self, rgb: np.ndarray, eye_iterations: int) -> None:
        """The emission `eye_iterations` complete eye iterations saw, summed
        per pixel ((pixels, 3)) elsewhere, and their count in the average."""
        self.emission += rgb
        self.eye_iterations += int(eye_iterations)

    def gather_box(self) -> np.ndarray | None:
        """Bounding box of the hit points grown by the largest radius: the
        photon culling box of §4.3 (None before the first iteration)."""
        if len(self.hit_points) == 0:
            return None
        return reach_box(self.hit_points.position, self.radius[self.hit_points.pixel])

    # -- photon batches -----------------------------------------------------
    def apply_photons(self, deposits: PhotonDeposits | list, emitted: int, materials,
                      gather: str = "grid", threads: int = 2, reorder: bool = True,
                      hash_options: dict | None = None) -> None:
        """One statistics update for a batch of deposits (a PhotonDeposits,
        or a list of the parts it arrived in) from `emitted` photon paths
        (eqs. 1-4): `gather_sums`, then `apply_sums`."""
        hp = self.hit_points
        parts = deposits if isinstance(deposits, list) else [deposits]
        if len(hp) == 0 or not any(len(p) for p in parts):
            self.photons_emitted += int(emitted)
            return
        if gather not in GATHERS:
            raise ValueError(f"unknown gather {gather!r} (known: {', '.join(GATHERS)})")
        if self.fit:
            self._fit_to_density(parts, hp, materials, threads)
        m, phi = gather_sums(parts, hp, self.radius[hp.pixel], materials, gather, threads,
                             reorder, hash_options)
        self.apply_sums(hp.pixel, m, phi, emitted)

    def apply_sums(self, pixel: np.ndarray, m: np.ndarray, phi: np.ndarray, emitted: int) -> None:
        """One statistics update (eqs. 1-4) from a batch's per-pixel sums:
        M (photons within the radius) and Phi (their BSDF-weighted flux),
        gathered at the current radii, summed over whoever held the batch's
        deposits; `emitted` photon paths made the batch. The same arithmetic
        as `apply_photons`, which is this after its own gather."""
        self.photons_emitted += int(emitted)
        if len(pixel):
            self._update(np.asarray(pixel), np.asarray(m, np.float64), np.asarray(phi, np.float64))

    def _update(self, pixel: np.ndarray, m: np.ndarray, phi: np.ndarray) -> None:
        for name in ("photon_count", "radius", "tau"):      # a checkpoint's arrays may be views
            a = getattr(self, name)
            if not (a.flags.c_contiguous and a.dtype == np.float64):
                setattr(self, name, np.ascontiguousarray(a, np.float64))
        _update_pixels(np.ascontiguousarray(pixel, np.int64), np.ascontiguousarray(m, np.float64),
                       np.ascontiguousarray(phi, np.float64), float(self.alpha),
                       self.photon_count, self.radius, self.tau)

    # -- the image ------------------------------------------------------------
    def radiance(self) -> np.ndarray:
        """Eq. 5 plus the directly seen emission: (H, W, 3) float64."""
        img = np.zeros_like(self.tau)
        if self.photons_emitted > 0:
            area = math.pi * self.radius ** 2
            img += self.tau / (self.photons_emitted * area)[:, None]
        if self.eye_iterations:
            img += self.emission / self.eye_iterations
        return img.reshape(self.height, self.width, 3)
