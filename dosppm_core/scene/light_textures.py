"""Textured lights: Mitsuba 3's spot with a `texture`, projector with an
`irradiance` image and area light with a `radiance` texture
(src/emitters/spot.cpp, projector.cpp, area.cpp).

Both send out, in direction d (local frame: x the image's horizontal, z
the light's axis), their untextured value times the texel at

* spot:      uv = (1/2 + x / (2 z tan cutoff), 1/2 + y / (2 z tan cutoff)),
  the image spanning the cutoff cone's square, times the spot's falloff;
* projector: uv = (1/2 - x / (2 z tan_x), 1/2 - y / (2 z tan_y)), the image
  filling the frustum (Mitsuba's perspective_projection mirrors x and y),
  times pi / cos^3 (the plane at distance 1 gets pi E).

`kernels.texture.emitter_texel` evaluates that texel for the photons and
the shadow rays; here is the flux a light's power (and so the light
choice) needs: the integral over directions of what it sends out.

An area light's radiance at a point is its material's `emission` times
the texel at the point's uv. Its texture is kept divided by its mean
texel (`normalised`) and `emission` multiplied by it, so the triangles'
power (pi area emission), which the light choice, the light tree and the
BSDF-sampled rays' MIS weights all read, counts the texture on average
without a per-triangle integral; photons and shadow rays that sample a
point of the triangle uniformly multiply by the texel there.
"""
from __future__ import annotations

import math

import numpy as np

from dosppm_core.scene.textures import CHECKERBOARD, CLAMP, MIRROR, NEAREST, REPEAT, Texture

# Quadrature of the spot's cone: (cos theta, phi) cells, one texel lookup each.
SPOT_CELLS = (256, 512)
# The projector's image plane: this many cells per texel along each side.
PROJECTOR_CELLS_PER_TEXEL = 2


def textured_flux(projector: bool, cone: np.ndarray, texture: Texture) -> np.ndarray:
    """RGB flux per unit value (intensity or irradiance) of a textured
    spot or projector (`LightTable.cone` conventions)."""
    if projector:
        return _projector_flux(cone, texture)
    return _spot_flux(cone, texture)


def normalised(texture: Texture) -> tuple[Texture, np.ndarray]:
    """(texture divided by its mean texel per channel, that mean); a
    channel whose mean is 0 stays as it is (black)."""
    mean = texture.texels.reshape(-1, 3).astype(np.float64).mean(axis=0)
    safe = np.where(mean > 0, mean, 1.0)
    scaled = Texture(texture.name, texture.kind, np.ascontiguousarray(texture.texels / safe, np.float32),
                     texture.filter, texture.wrap, texture.uv_map)
    return scaled, mean


def lookup(texture: Texture, s: np.ndarray, r: np.ndarray) -> np.ndarray:
    """(n, 3) texels at texture coordinates (s, r): `kernels.texture.texel`
    in numpy (the scene layer imports no kernel), for the flux integrals."""
    a = texture.uv_map
    u, v = a[0] * s + a[1] * r + a[2], a[3] * s + a[4] * r + a[5]
    tex = texture.texels.astype(np.float64)
    h, w = tex.shape[:2]
    if texture.kind == CHECKERBOARD:
        same = (u - np.floor(u) > 0.5) == (v - np.floor(v) > 0.5)
        return np.where(same[:, None], tex[0, 0], tex[0, 1])
    if texture.filter == NEAREST:
        return tex[_wrap(np.floor(v * h), h, texture.wrap), _wrap(np.floor(u * w), w, texture.wrap)]
    fx, fy = u * w - 0.5, v * h - 0.5
    x0, y0 = np.floor(fx), np.floor(fy)
    ax, ay = (fx - x0)[:, None], (fy - y0)[:, None]
    xa, xb = _wrap(x0, w, texture.wrap), _wrap(x0 + 1, w, texture.wrap)
    ya, yb = _wrap(y0, h, texture.wrap), _wrap(y0 + 1, h, texture.wrap)
    return ((1 - ax) * (1 - ay) * tex[ya, xa] + ax * (1 - ay) * tex[ya, xb]
            + (1 - ax) * ay * tex[yb, xa] + ax * ay * tex[yb, xb])


def _wrap(i: np.ndarray, size: int, mode: int) -> np.ndarray:
    """Texel indices wrapped into [0, size) (`kernels.texture.wrap_index`)."""
    i = np.clip(np.nan_to_num(i, nan=-1e9), -1e9, 1e9).astype(np.int64)
    if mode == REPEAT:
        return np.mod(i, size)
    if mode == MIRROR:
        i = np.mod(i, 2 * size)
        return np.where(i >= size, 2 * size - 1 - i, i)
    assert mode == CLAMP
    return np.clip(i, 0, size - 1)


def _spot_flux(cone: np.ndarray, texture: Texture) -> np.ndarray:
    """Midpoint rule over d(cos theta) d(phi) of falloff x texel."""
    cos_cut, cutoff, beam = cone[0], cone[2], cone[3]
    nt, nphi = SPOT_CELLS
    z = 1.0 - (np.arange(nt) + 0.5) / nt * (1.0 - cos_cut)
    phi = (np.arange(nphi) + 0.5) / nphi * 2 * math.pi
    z, phi = np.meshgrid(z, phi, indexing="ij")
    sin_t = np.sqrt(np.maximum(0.0, 1.0 - z * z))
    theta = np.arccos(np.minimum(1.0, z))
    fall = np.where(theta <= beam, 1.0, np.clip((cutoff - theta) / max(cutoff - beam, 1e-300), 0.0, 1.0))
    k = 0.5 / (z * math.tan(cutoff))
    rgb = lookup(texture, (0.5 + sin_t * np.cos(phi) * k).ravel(), (0.5 + sin_t * np.sin(phi) * k).ravel())
    cell = (1.0 - cos_cut) / nt * 2 * math.pi / nphi
    return (rgb * (fall.ravel() * cell)[:, None]).sum(axis=0)


def _projector_flux(cone: np.ndarray, texture: Texture) -> np.ndarray:
    """pi x the image plane's area x the mean texel over it (Mitsuba's
    sample_ray weight: pi E(uv) area / pdf(uv))."""
    h, w = texture.texels.shape[:2]
    nu, nv = PROJECTOR_CELLS_PER_TEXEL * w, PROJECTOR_CELLS_PER_TEXEL * h
    s, r = np.meshgrid((np.arange(nu) + 0.5) / nu, (np.arange(nv) + 0.5) / nv)
    mean = lookup(texture, s.ravel(), r.ravel()).mean(axis=0)
    return math.pi * 4.0 * cone[0] * cone[1] * mean
