"""The environment light's map: texels as Mitsuba 3's `envmap` lays them
out, and the tables that sample it by luminance.

A latitude-longitude image of H rows and W columns becomes texels of
shape (H, W + 1, 3): the first column repeated at the end (periodic in
phi), scale applied. Texel row i sits at theta = i pi / (H - 1); texel
column j at u = (j + 1/2) / W, where u = phi / 2 pi and the local
direction is (sin phi sin theta, cos theta, -cos phi sin theta) (y up).
Radiance between texels is bilinear, exactly as Mitsuba evaluates it
(`kernels.envmap.env_eval`). A `constant` emitter is a 2x2 map of one
value.

Sampling (`distribution`) is piecewise constant in solid angle over the
(H - 1) x W patches between texels: a patch's weight is the mean
luminance of its four corners times its solid angle dphi (cos theta_i -
cos theta_i+1), the sin(theta) weighting in closed form. Every direction
whose bilinear radiance is non-zero lies in a patch of positive weight.

Bad input raises ValueError (the scene readers turn it into a SceneError
naming the element): the model imports this module, not the reverse.
"""
from __future__ import annotations

import math

import numpy as np

# Mitsuba's luminance() of linear sRGB.
LUMINANCE = np.array([0.212671, 0.715160, 0.072169])


def texels_from_image(rgb, scale: float = 1.0) -> np.ndarray:
    """(H, W, 3) linear RGB, lat-long, as Mitsuba reads it -> texels."""
    img = np.asarray(rgb, np.float64)
    if img.ndim != 3 or img.shape[2] != 3 or img.shape[0] < 3 or img.shape[1] < 2:
        raise ValueError(f"environment map must be at least 2x3 RGB pixels, got shape {img.shape}")
    img = np.concatenate([img, img[:, :1]], axis=1) * float(scale)
    return np.ascontiguousarray(img, np.float32)


def constant_texels(radiance) -> np.ndarray:
    """The texels of a uniform environment of `radiance` (RGB)."""
    return np.ascontiguousarray(np.broadcast_to(np.asarray(radiance, np.float32), (2, 2, 3)))


def load_image(path: str) -> np.ndarray:
    """An EXR environment map's linear RGB (H, W, 3)."""
    from dosppm_core.film import FilmError, read_exr
    if not path.lower().endswith(".exr"):
        raise ValueError(f"environment maps are read from OpenEXR files only, got {path!r}")
    try:
        rgb, _layers = read_exr(path)
    except FilmError as e:
        raise ValueError(str(e)) from None
    return rgb


def _patches(texels: np.ndarray):
    """(mean RGB of each patch's four corners (H-1, W, 3), solid angle of
    each patch row (H-1,))."""
    t = np.asarray(texels, np.float64)
    h, w = t.shape[0], t.shape[1] - 1
    corners = 0.25 * (t[:-1, :-1] + t[:-1, 1:] + t[1:, :-1] + t[1:, 1:])
    cos_theta = np.cos(np.arange(h) * math.pi / (h - 1))
    solid = (2 * math.pi / w) * (cos_theta[:-1] - cos_theta[1:])
    return corners, solid


def radiance_integral(texels: np.ndarray) -> np.ndarray:
    """The integral of the radiance over the sphere, RGB (patch means
    times solid angles: what picks the light by power; the photons'
    flux is exact whatever it is)."""
    corners, solid = _patches(texels)
    return (corners * solid[:, None, None]).sum(axis=(0, 1))


def distribution(texels: np.ndarray) -> tuple:
    """The sampling tables the kernels take with the texels
    (`kernels.envmap`): (row cdf (H,), column cdf per row (H-1, W+1),
    solid-angle pdf per patch (H-1, W)). A black map gets an all-zero pdf."""
    corners, solid = _patches(texels)
    weight = np.maximum(corners @ LUMINANCE, 0.0)                  # (H-1, W)
    mass = weight * solid[:, None]
    total = mass.sum()
    h1, w = weight.shape
    row_cdf = np.zeros(h1 + 1)
    col_cdf = np.zeros((h1, w + 1))
    if not total > 0:
        col_cdf[:, 1:] = np.linspace(1.0 / w, 1.0, w)
        row_cdf[1:] = np.linspace(1.0 / h1, 1.0, h1)
        return row_cdf, col_cdf, np.zeros((h1, w))
    np.cumsum(mass.sum(axis=1) / total, out=row_cdf[1:])
    row_cdf[-1] = 1.0
    rows = weight.sum(axis=1)
    safe = np.where(rows > 0, rows, 1.0)
    np.cumsum(weight / safe[:, None], axis=1, out=col_cdf[:, 1:])
    col_cdf[:, -1] = 1.0
    return row_cdf, col_cdf, weight / total
