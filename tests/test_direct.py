"""Direct light by shadow rays (next-event estimation) against closed forms.

A diffuse plane lit by one light, seen from between the plane and the
light: every pixel's radiance is rho / pi * E(x) at the point x its eye
ray meets, with E from the light in closed form. Photons add nothing here
(with shadow rays they deposit only from their second surface, and the
plane is the only surface), so the image is the shadow rays' alone, and
with one light it is nearly noiseless.
"""
from __future__ import annotations

import math

import numpy as np
import pytest

from dosppm_core.modes.sppm import render
from dosppm_core.scene.model import Camera, Material, SceneBuilder
from dosppm_core.settings import RenderSettings
from dosppm_core.trace import LIGHT_CACHE

RHO = 0.5
SIZE = 24


def _plane_scene(add_light, floor: Material | None = None) -> tuple:
    b = SceneBuilder(name="plane")
    b.add_material(floor or Material("floor", "diffuse", (RHO, RHO, RHO), two_sided=False))
    big = 20.0
    b.add_mesh(np.array([[-big, -big, 0], [big, -big, 0], [big, big, 0], [-big, big, 0]], float),
               [(0, 1, 2), (0, 2, 3)], "floor", "floor")          # CCW from above: faces +z
    add_light(b)
    b.camera = Camera((0, 0, 0.8), (0, 0, 0), (0, 1, 0), 70, SIZE, SIZE)
    return b.build()


def _pixel_points(scene, sub: int = 8) -> np.ndarray:
    """Where eye rays through a sub x sub grid in each pixel meet the plane
    z = 0, (H, W, sub * sub, 3): the renderer's box filter averages a
    pixel's radiance over its footprint, and so does the expected value."""
    f = scene.camera.frame()
    pos, right, up, fwd, (tx, ty) = f[0], f[1], f[2], f[3], f[4, :2]
    offs = (np.arange(sub) + 0.5) / sub
    cols = (2.0 * (np.arange(SIZE)[:, None] + offs[None, :]) / SIZE - 1.0) * tx      # (W, sub)
    rows = (1.0 - 2.0 * (np.arange(SIZE)[:, None] + offs[None, :]) / SIZE) * ty      # (H, sub)
    sx = cols[None, :, None, :, None]
    sy = rows[:, None, :, None, None]
    d = fwd + sx * right + sy * up                                                    # (H, W, sub, sub, 3)
    t = -pos[2] / d[..., 2]
    return (pos + t[..., None] * d).reshape(SIZE, SIZE, sub * sub, 3)


def _render(scene, iterations=64):
    return render(scene, RenderSettings(photons_per_iteration=10_000), iterations=iterations)[..., 0]


def test_point_light_above_a_plane():
    light, intensity = np.array([0.3, -0.2, 1.0]), 2.0
    scene = _plane_scene(lambda b: b.add_point_light(light, (intensity,) * 3, "lamp"))
    x = _pixel_points(scene)
    d = light - x
    dist = np.linalg.norm(d, axis=-1)
    expected = (RHO / math.pi * intensity * (d[..., 2] / dist) / dist ** 2).mean(-1)
    got = _render(scene)
    np.testing.assert_allclose(got, expected, rtol=0.01)


def test_spot_light_cone_and_falloff():
    light, intensity, cutoff, beam = np.array([0.0, 0.0, 1.0]), 3.0, 30.0, 20.0
    scene = _plane_scene(lambda b: b.add_spot_light(light, (0, 0, 0), (intensity,) * 3, cutoff, beam, "spot"))
    x = _pixel_points(scene)
    d = light - x
    dist = np.linalg.norm(d, axis=-1)
    theta = np.degrees(np.arccos(d[..., 2] / dist))
    fall = np.clip((cutoff - theta) / (cutoff - beam), 0.0, 1.0)
    expected = (RHO / math.pi * intensity * fall * (d[..., 2] / dist) / dist ** 2).mean(-1)
    got = _render(scene)
    # Inside the beam every pixel matches; on the falloff ramp (a quarter
    # of the intensity per pixel) a few dozen jittered samples per pixel
    # leave ~1% noise, so the ramp is compared as a whole.
    theta = theta.mean(-1)
    pixel_deg = 70.0 / SIZE
    beam_px = theta < beam - pixel_deg
    np.testing.assert_allclose(got[beam_px], expected[beam_px], rtol=0.01)
    ramp = (theta > beam + pixel_deg) & (theta < cutoff - pixel_deg)
    assert got[ramp].sum() == pytest.approx(expected[ramp].sum(), rel=0.01)
    assert got.mean() == pytest.approx(expected.mean(), rel=0.01)
    assert got[theta > cutoff + pixel_deg].max() == 0.0
    assert (got[theta < beam] > 0).all()


def test_small_area_light_above_a_plane():
    c, s, radiance = np.array([0.2, 0.1, 1.0]), 0.02, 500.0
    quad = c + np.array([[-s, -s, 0], [-s, s, 0], [s, s, 0], [s, -s, 0]]) / 2

    def lamp(b):
        b.add_material(Material("lamp", "diffuse", (0, 0, 0), emission=(radiance,) * 3, two_sided=False))
        b.add_mesh(quad, [(0, 1, 2), (0, 2, 3)], "lamp", "lamp")    # CCW from below: faces -z
    scene = _plane_scene(lamp)
    x = _pixel_points(scene)
    d = c - x
    dist = np.linalg.norm(d, axis=-1)
    cos = d[..., 2] / dist            # at the plane and at the light alike (parallel)
    expected = (RHO / math.pi * radiance * s * s * cos * cos / dist ** 2).mean(-1)
    got = _render(scene)
    # One sample per iteration on a light 1/50 of its distance wide: the
    # point approximation and the noise are both well under 2%.
    np.testing.assert_allclose(got, expected, rtol=0.03)
    assert got.mean() == pytest.approx(expected.mean(), rel=0.01)


def test_a_lamp_seen_low_from_a_floor_far_from_the_origin_does_not_shadow_itself():
    """A floor patch 16 m from the origin lit by a small ceiling lamp 6 m
    away and 2.5 m up, as in the generated building. The shadow ray leaves
    the floor lifted by the spawn offset (relative to |p|); aimed from the
    hit point instead of from where it starts, it ran on past the lamp and
    the lamp shadowed itself (the building's floor read 10% dark)."""
    c, s, radiance = np.array([10.0, 0.0, 2.5]), 0.05, 2000.0
    quad = c + np.array([[-s, -s, 0], [-s, s, 0], [s, s, 0], [s, -s, 0]]) / 2

    def lamp(b):
        b.add_material(Material("lamp", "diffuse", (0, 0, 0), emission=(radiance,) * 3, two_sided=False))
        b.add_mesh(quad, [(0, 1, 2), (0, 2, 3)], "lamp", "lamp")    # faces -z
    scene = _plane_scene(lamp)
    scene.camera = Camera((16, 0, 0.8), (16, 0, 0), (0, 1, 0), 70, SIZE, SIZE)
    x = _pixel_points(scene)
    d = c - x
    dist = np.linalg.norm(d, axis=-1)
    cos = d[..., 2] / dist            # at the floor and at the lamp alike (parallel)
    expected = (RHO / math.pi * radiance * s * s * cos * cos / dist ** 2).mean(-1)
    got = _render(scene, iterations=64)
    assert got.mean() == pytest.approx(expected.mean(), rel=0.01)
    np.testing.assert_allclose(got, expected, rtol=0.05)     # the jitter in a pixel: 2% at most


def _many_lamps(rng, n):
    """n point lamps of assorted power, some near the plane, most far."""
    pos = np.c_[rng.uniform(-4, 4, n), rng.uniform(-4, 4, n), rng.uniform(0.3, 3.0, n)]
    return pos, rng.uniform(0.2, 4.0, n)


def test_many_lights_chosen_by_their_contribution_stay_unbiased():
    """Forty point lamps above the plane: the light chosen by the light
    tree and the cells the photons taught gives the closed-form sum of all
    forty, per pixel and over the image."""
    pos, power = _many_lamps(np.random.default_rng(7), 40)

    def lamps(b):
        for k in range(len(pos)):
            b.add_point_light(pos[k], (power[k],) * 3, f"lamp{k}")
    scene = _plane_scene(lamps)
    x = _pixel_points(scene)
    expected = np.zeros(x.shape[:2])
    for p, i in zip(pos, power):
        d = p - x
        dist = np.linalg.norm(d, axis=-1)
        expected += (RHO / math.pi * i * (d[..., 2] / dist) / dist ** 2).mean(-1)
    got = _render(scene, iterations=256)
    assert got.mean() == pytest.approx(expected.mean(), rel=0.01)
    # Per 2x2 pixels: one shadow ray a pixel and iteration among forty
    # lamps leaves about 4% noise per pixel (measured), 2% per block: 5 sigma.
    np.testing.assert_allclose(_blocks(got), _blocks(expected), rtol=0.1)


def _blocks(img, k=2):
    h, w = img.shape
    return img.reshape(h // k, k, w // k, k).mean(axis=(1, 3))


def _walled_scene(pos, power):
    """The plane cut by a black wall x = 0 far higher and longer than the
    lamps' reach; the camera sees only the side x < 0."""
    def lamps(b):
        b.add_material(Material("wall", "diffuse", (0.0, 0.0, 0.0)))
        b.add_mesh(np.array([[0, -100, -1], [0, 100, -1], [0, 100, 50], [0, -100, 50]], float),
                   [(0, 1, 2), (0, 2, 3)], "wall", "wall")
        for k in range(len(pos)):
            b.add_point_light(pos[k], (power[k],) * 3, f"lamp{k}")
    scene = _plane_scene(lamps)
    scene.camera = Camera((-2, 0, 0.8), (-2, 0, 0), (0, 1, 0), 70, SIZE, SIZE)
    return scene


def test_lamps_behind_a_wall_are_learned_away_and_the_image_stays_exact():
    """Eight lamps on the camera's side of an opaque wall, twenty-four
    behind it. The light tree cannot see the wall and sends most shadow
    rays to the hidden lamps; the photons' first hits teach each cell of
    the floor that only the near lamps reach it, so after a few iterations
    the hidden lamps keep only the tree's defensive share. The image is
    the near lamps' closed form either way."""
    from dosppm_core.kernels.direct import choice_pmf
    from dosppm_core.modes.sppm import Renderer
    rng = np.random.default_rng(11)
    near = np.c_[rng.uniform(-4, -0.5, 8), rng.uniform(-4, 4, 8), rng.uniform(0.3, 3.0, 8)]
    far = np.c_[rng.uniform(0.5, 4, 24), rng.uniform(-4, 4, 24), rng.uniform(0.3, 3.0, 24)]
    pos, power = np.r_[near, far], rng.uniform(0.5, 3.0, 32)
    scene = _walled_scene(pos, power)
    x = _pixel_points(scene)
    expected = np.zeros(x.shape[:2])
    for p, i in zip(near, power[:8]):
        d = p - x
        dist = np.linalg.norm(d, axis=-1)
        expected += (RHO / math.pi * i * (d[..., 2] / dist) / dist ** 2).mean(-1)
    r = Renderer(scene, RenderSettings(photons_per_iteration=30_000))
    try:
        hidden_tree = []
        for it in range(256):
            r.run_iteration()
            if it == 0:
                at = (-2.0, 0.0, 0.0, 0.0, 0.0, 1.0)
                hidden_tree = [choice_pmf(r.lights[:LIGHT_CACHE], r.lights[LIGHT_CACHE], *at, li) for li in range(8, 32)]
        got = r.image()[..., 0]
        hidden = [choice_pmf(r.lights[:LIGHT_CACHE], r.lights[LIGHT_CACHE], *at, li) for li in range(8, 32)]
    finally:
        r.close()
    assert sum(t for _, t, _ in hidden_tree) > 0.5          # the tree alone: most choices behind the wall
    assert all(c == 0.0 for _, _, c in hidden)             # no photon from behind reached the cell
    assert sum(m for m, _, _ in hidden) < 0.1               # the mixture: the tree's defensive share only
    assert got.mean() == pytest.approx(expected.mean(), rel=0.01)
    np.testing.assert_allclose(_blocks(got), _blocks(expected), rtol=0.1)    # 2% noise a block


def test_paper_estimator_blurs_the_same_light():
    """--direct photons still renders the plane (by photon density), to the
    same mean within its bias and noise."""
    light = np.array([0.0, 0.0, 1.0])
    scene = _plane_scene(lambda b: b.add_point_light(light, (1.0,) * 3, "lamp"))
    nee = _render(scene, iterations=8)
    photons = render(scene, RenderSettings(direct="photons", photons_per_iteration=100_000),
                     iterations=8)[..., 0]
    assert photons.mean() == pytest.approx(nee.mean(), rel=0.05)
    assert np.abs(photons - nee).max() > 0.01 * nee.max()     # not the same estimator


@pytest.mark.parametrize("size", [0.02, 0.6])
def test_glossy_plane_under_an_area_light(size):
    """A GGX plane under a square lamp. Small lamp: the closed form f cos Le
    A cos_y / d^2 per pixel (f barely changes across it), which both MIS
    techniques must add up to. Large lamp (its highlight sharper than the
    lamp): against the same renderer at 4x the iterations, image and
    tiles, as both converge to the integral."""
    alpha, radiance = 0.3, 50.0
    c = np.array([0.1, 0.05, 1.0])
    quad = c + np.array([[-size, -size, 0], [-size, size, 0], [size, size, 0], [size, -size, 0]]) / 2

    def lamp(b):
        b.add_material(Material("lamp", "diffuse", (0, 0, 0), emission=(radiance,) * 3, two_sided=False))
        b.add_mesh(quad, [(0, 1, 2), (0, 2, 3)], "lamp", "lamp")
    floor = Material("floor", "glossy", (RHO, RHO, RHO), roughness=alpha, two_sided=False)
    scene = _plane_scene(lamp, floor)
    if size < 0.1:
        from dosppm_core.kernels.bsdf import eval_bsdf
        x = _pixel_points(scene, sub=4)
        wi = c - x
        dist = np.linalg.norm(wi, axis=-1)
        wi /= dist[..., None]
        wo = scene.camera.frame()[0] - x
        wo /= np.linalg.norm(wo, axis=-1)[..., None]
        f = np.vectorize(lambda a, b, c_, d, e, g: eval_bsdf(3, alpha, 0.0, 0.0, 1.0, a, b, c_, d, e, g))(
            wo[..., 0], wo[..., 1], wo[..., 2], wi[..., 0], wi[..., 1], wi[..., 2])
        expected = (RHO * f * wi[..., 2] * radiance * size * size * wi[..., 2] / dist ** 2).mean(-1)
        got = _render(scene, iterations=256)
        assert got.mean() == pytest.approx(expected.mean(), rel=0.02)
        np.testing.assert_allclose(got, expected, rtol=0.25)
    else:
        a = _render(scene, iterations=64)
        b = _render(scene, iterations=256)
        assert a.mean() == pytest.approx(b.mean(), rel=0.02)
        tiles = lambda img: img.reshape(4, SIZE // 4, 4, SIZE // 4).mean(axis=(1, 3))
        np.testing.assert_allclose(tiles(a), tiles(b), rtol=0.15)   # tiles: 3.6% noise at 64 iterations
