"""Image error metrics for comparing a render with a reference.

relMSE (relative mean squared error) is the figure the photon-mapping
literature reports; RMSE is kept for absolute comparisons. SPPM is
consistent but biased at any finite iteration (the kernel radius blurs
illumination), so two more figures separate bias from noise: the relative
difference of mean luminance (a global energy check) and the relMSE of
Gaussian-blurred images (blurring averages noise away, bias survives).

Every metric rejects NaN and Inf: one bad pixel would otherwise decide the
number silently.
"""
from __future__ import annotations

import math

import numpy as np

from dosppm_core.film import write_png_rgb8

# Rec.709 / sRGB primaries, linear light.
REC709_LUMINANCE = np.array([0.2126, 0.7152, 0.0722])


def rmse(a, b) -> float:
    """Root mean squared error over pixels and channels."""
    a, b = _pair(a, b)
    return float(np.sqrt(np.mean((a - b) ** 2)))


def relmse(a, ref, eps: float = 1e-2) -> float:
    """Mean over pixels and channels of (a - ref)^2 / (ref^2 + eps); `eps`
    keeps black reference pixels from dominating."""
    a, ref = _pair(a, ref, ("a", "ref"))
    return float(np.mean((a - ref) ** 2 / (ref * ref + eps)))


def seed_noise(a, b, eps: float = 1e-2) -> float:
    """The relMSE one render of two independent seeds, `a` and `b`, has
    from noise alone, with no reference: E[(a - b)^2] = 2 var per pixel, so
    the mean of (a - b)^2 / (2 (m^2 + eps)), m = (a + b) / 2 their mean.
    relmse(a, b) / 2 would divide by one seed's own noisy value instead: a
    pixel that is black in b and bright in a (a rare path found once) then
    weighs m^2 / eps, and a few such pixels decide the figure (on a
    600-light building, 0.79 where this gives 0.016)."""
    a, b = _pair(a, b)
    m = 0.5 * (a + b)
    return float(np.mean((a - b) ** 2 / (2.0 * (m * m + eps))))


def luminance(img) -> np.ndarray:
    """Rec.709 luminance Y of a linear RGB (..., 3) image."""
    img = np.asarray(img, dtype=np.float64)
    if img.shape[-1:] != (3,):
        raise ValueError(f"expected an RGB (..., 3) image, got shape {img.shape}")
    return img @ REC709_LUMINANCE


def mean_luminance_bias(a, ref) -> float:
    """(mean Y(a) - mean Y(ref)) / mean Y(ref): +0.02 means `a` carries 2%
    more energy than the reference."""
    a, ref = _pair(a, ref, ("a", "ref"))
    y_ref = float(np.mean(luminance(ref)))
    if y_ref <= 0:
        raise ValueError("reference has zero mean luminance: relative bias is undefined")
    return (float(np.mean(luminance(a))) - y_ref) / y_ref


def blurred_relmse(a, ref, sigma: float, eps: float = 1e-2, where=None) -> float:
    """relMSE of both images after a Gaussian blur of `sigma` pixels: what
    remains after noise is averaged away is mostly bias. `where` (H, W)
    bool: score only those pixels, and blur only over them (normalised
    convolution), so that unscored pixels, such as a mirror whose limit
    differs, cannot leak a constant error into their scored neighbours."""
    a, ref = _pair(a, ref, ("a", "ref"))
    if where is None:
        return relmse(gaussian_blur(a, sigma), gaussian_blur(ref, sigma), eps)
    w = np.asarray(where, dtype=np.float64).reshape(where.shape + (1,) * (a.ndim - 2))
    norm = np.maximum(gaussian_blur(w, sigma), 1e-12)
    a, ref = gaussian_blur(a * w, sigma) / norm, gaussian_blur(ref * w, sigma) / norm
    return relmse(a[where], ref[where], eps)


def gaussian_blur(img, sigma: float) -> np.ndarray:
    """Separable Gaussian blur over the first two axes, mirrored edges;
    sigma <= 0 returns a copy."""
    out = np.array(img, dtype=np.float64)
    if sigma <= 0:
        return out
    radius = max(1, int(math.ceil(3.0 * sigma)))
    taps = np.exp(-0.5 * (np.arange(-radius, radius + 1) / sigma) ** 2)
    taps /= taps.sum()
    for axis in (0, 1):
        out = _convolve_axis(out, taps, axis)
    return out


def _convolve_axis(img: np.ndarray, taps: np.ndarray, axis: int) -> np.ndarray:
    radius = len(taps) // 2
    n = img.shape[axis]
    padded = np.take(img, _mirror_indices(n, radius), axis=axis)
    out = np.zeros_like(img)
    for k, w in enumerate(taps):
        out += w * np.take(padded, np.arange(k, k + n), axis=axis)
    return out


def _mirror_indices(n: int, radius: int) -> np.ndarray:
    """Indices of a length-n axis padded by `radius` on each side, mirrored
    about the edge pixels (numpy's 'reflect'), valid even when radius >= n."""
    idx = np.arange(-radius, n + radius)
    if n == 1:
        return np.zeros_like(idx)
    period = 2 * n - 2
    idx = idx % period
    return np.where(idx >= n, period - idx, idx)


def tile_means(img, tiles) -> np.ndarray:
    """Mean of each tile of a (H, W[, C]) image split into `tiles` = (rows,
    cols) or one int for both; edges are rounded so tiles differ by at most
    one pixel. Returns (rows, cols[, C])."""
    img = np.asarray(img, dtype=np.float64)
    rows, cols = (tiles, tiles) if np.isscalar(tiles) else tiles
    h, w = img.shape[:2]
    if not (1 <= rows <= h and 1 <= cols <= w):
        raise ValueError(f"cannot split a {h}x{w} image into {rows}x{cols} tiles")
    y_edges = np.linspace(0, h, rows + 1).round().astype(int)
    x_edges = np.linspace(0, w, cols + 1).round().astype(int)
    sums = np.add.reduceat(np.add.reduceat(img, y_edges[:-1], axis=0), x_edges[:-1], axis=1)
    counts = np.outer(np.diff(y_edges), np.diff(x_edges))
    return sums / counts.reshape(counts.shape + (1,) * (img.ndim - 2))


def relative_difference(a, b, eps: float = 1e-2) -> np.ndarray:
    """Per-pixel (Y(a) - Y(b)) / (Y(b) + eps) on luminance; positive where
    `a` is brighter."""
    a, b = _pair(a, b)
    y_b = luminance(b)
    return (luminance(a) - y_b) / (np.abs(y_b) + eps)


def difference_png(path: str, a, b, scale: float | None = None, eps: float = 1e-2) -> float:
    """Write a false-colour map of the relative difference of `a` to `b`:
    blue where a is darker, white where equal, red where brighter, saturating
    at +-`scale` (default: the 99th percentile of |difference|). Returns the
    scale used so a caption can state it."""
    diff = relative_difference(a, b, eps)
    if scale is None:
        scale = float(np.percentile(np.abs(diff), 99))
    scale = max(float(scale), 1e-6)
    t = np.clip(diff / scale, -1.0, 1.0)
    write_png_rgb8(path, _diverging_colours(t))
    return scale


def _diverging_colours(t: np.ndarray) -> np.ndarray:
    """t in [-1, 1] -> uint8 RGB through matplotlib's 'bwr' if installed,
    else the same blue-white-red ramp built here."""
    try:
        from matplotlib import colormaps  # optional (the [bench] extra), and 0.3 s to import
        rgba = colormaps["bwr"](0.5 * (t + 1.0))
        return np.round(rgba[..., :3] * 255).astype(np.uint8)
    except ImportError:
        pass
    pos, neg = np.clip(t, 0, 1), np.clip(-t, 0, 1)
    rgb = np.stack([1.0 - neg, 1.0 - pos - neg, 1.0 - pos], axis=-1)
    return np.round(rgb * 255).astype(np.uint8)


def _pair(a, b, names=("a", "b")) -> tuple[np.ndarray, np.ndarray]:
    a = np.asarray(a, dtype=np.float64)
    b = np.asarray(b, dtype=np.float64)
    if a.shape != b.shape:
        raise ValueError(f"shape mismatch: {names[0]} is {a.shape}, {names[1]} is {b.shape}")
    if a.size == 0:
        raise ValueError("empty images")
    for name, arr in zip(names, (a, b)):
        if not np.all(np.isfinite(arr)):
            raise ValueError(f"{name} contains NaN or Inf ({int(np.sum(~np.isfinite(arr)))} values)")
    return a, b
