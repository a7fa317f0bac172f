"""Shared by the cluster tests: the single-process SPPM reference and the
per-tile comparison within noise."""
from __future__ import annotations

import functools

import numpy as np

from dosppm_core.modes.sppm import Renderer
from dosppm_core.settings import RenderSettings
from tests.helpers.scenes import small_scene

ITERATIONS = 6
SIZE = 64


def settings(seed=5):
    return RenderSettings(seed=seed, photons_per_iteration=40_000, photons_per_job=1024,
                          tile_pixels=1024, threads=1)


def tiles(img, n=8):
    h, w = img.shape[:2]
    return img.reshape(n, h // n, n, w // n, 3).mean(axis=(1, 3))


def caustic_scene():
    return small_scene("cornell-caustic", SIZE)


@functools.lru_cache(maxsize=1)
def caustic_reference():
    """{seed: (image, progress)} of single-process SPPM on the glass and
    mirror spheres at 64x64, seeds 5 and 9 (the second measures noise)."""
    scene = caustic_scene()
    out = {}
    for seed in (5, 9):
        r = Renderer(scene, settings(seed))
        for _ in range(ITERATIONS):
            r.run_iteration()
        out[seed] = (r.image(), r.progress())
        r.close()
    return out


def assert_same_within_noise(img, ref, other_seed):
    """Per 8x8 tile, `img` differs from SPPM (same seed) by no more than
    SPPM differs from itself under another seed; the means agree to 2%."""
    t, t_ref, t_noise = tiles(img), tiles(ref), tiles(other_seed)
    scale = t_ref.mean()
    diff = np.abs(t - t_ref) / scale
    noise = np.abs(t_noise - t_ref) / scale
    assert np.isfinite(img).all()
    assert abs(img.mean() / ref.mean() - 1) < 0.02, f"mean off by {img.mean() / ref.mean() - 1:.2%}"
    assert np.median(diff) <= 2 * np.median(noise), (np.median(diff), np.median(noise))
    assert np.quantile(diff, 0.95) <= 2 * np.quantile(noise, 0.95), \
        (np.quantile(diff, 0.95), np.quantile(noise, 0.95))
