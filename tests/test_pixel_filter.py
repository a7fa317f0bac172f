"""The pixel reconstruction filter: each eye ray samples its film position
from the camera's filter (filter importance sampling, `kernels.emit`), as
Mitsuba's film weighs its samples with the filter (tabulated, clipped to
the film). Checked against the closed-form filter, Mitsuba's own table,
the jitter of the box filter as it was, and the scene reader."""
import dataclasses
import math
import os

import numba as nb
import numpy as np
import pytest

from dosppm_core.kernels import emit, rng
from dosppm_core.scene.mitsuba import load_mitsuba_xml as load_mitsuba
from dosppm_core.scene.model import Camera, SceneError, SceneHeader
from dosppm_core.trace import eye_ray_job
from tests.test_kernels import assert_chi2

STEPS = 31   # Mitsuba's MI_FILTER_RESOLUTION


def _ortho(width, height, **pixel_filter) -> Camera:
    """Looks down -z, image right +x and up +y; film x in [0, width] spans
    world x in [-1, 1], so an eye ray's origin gives its film position."""
    return Camera(position=(0.0, 0.0, 0.0), look_at=(0.0, 0.0, -1.0), up=(0.0, 1.0, 0.0), fov_deg=90.0,
                  width=width, height=height, projection="orthographic", **pixel_filter)


def _film_positions(cam: Camera, iterations: int, seed: int = 3):
    """(x, y) film coordinates and pixel of every eye ray of `iterations` iterations."""
    xs, ys, pixels = [], [], []
    n = cam.width * cam.height
    for it in range(iterations):
        origin, _, _ = emit.generate_eye_rays(cam.frame(), cam.width, np.uint64(seed), np.uint64(it), 0, n)
        o = origin.astype(np.float64)
        xs.append((o[:, 0] + 1.0) * cam.width / 2.0)
        ys.append((1.0 - o[:, 1] * cam.width / cam.height) * cam.height / 2.0)
        pixels.append(np.arange(n))
    return np.concatenate(xs), np.concatenate(ys), np.concatenate(pixels)


def _mitsuba_gaussian(x, stddev, radius):
    return np.maximum(0.0, np.exp(-x * x / (2 * stddev * stddev)) - math.exp(-radius * radius / (2 * stddev * stddev)))


def _expected_counts(value_at, radius, lo, hi, count):
    """Counts per step of the tabulated filter (step i of [0, radius) holds
    value_at(i * radius / STEPS), mirrored), clipped to [lo, hi]; the bin
    edges are the steps' edges within [lo, hi]."""
    h = radius / STEPS
    edges = np.arange(-STEPS, STEPS + 1) * h
    left, right = np.maximum(edges[:-1], lo), np.minimum(edges[1:], hi)
    keep = right > left
    index = np.abs(np.arange(-STEPS, STEPS))
    index = np.where(np.arange(-STEPS, STEPS) < 0, index - 1, index)   # step [-h, 0) mirrors [0, h)
    mass = value_at(index * h) * np.maximum(right - left, 0.0)
    bins = np.append(left[keep], right[keep][-1])
    return bins, count * mass[keep] / mass[keep].sum()


@pytest.mark.parametrize("name, pixel_filter, value_at", [
    ("gaussian", {"pixel_filter": "gaussian"}, lambda x: _mitsuba_gaussian(x, 0.5, 2.0)),
    ("gaussian 0.3", {"pixel_filter": "gaussian", "filter_stddev": 0.3}, lambda x: _mitsuba_gaussian(x, 0.3, 1.2)),
    ("tent", {"pixel_filter": "tent"}, lambda x: 1.0 - x),
    ("box 1.5", {"pixel_filter": "box", "filter_radius": 1.5}, np.ones_like),
])
def test_film_positions_follow_the_filter_clipped_to_the_film(name, pixel_filter, value_at):
    """Offsets from the pixel centre of interior pixels follow the whole
    tabulated filter; those of the first column, the part on the film."""
    cam = _ortho(40, 40, **pixel_filter)
    radius = cam.filter_radius_px()
    x, y, pixel = _film_positions(cam, 60)
    col, row = pixel % cam.width, pixel // cam.width
    dx, dy = x - (col + 0.5), y - (row + 0.5)
    inner = (col >= 2) & (col < cam.width - 2) & (row >= 2) & (row < cam.height - 2)
    for what, d, lo in ((f"{name}: x inside", dx[inner], -radius), (f"{name}: y inside", dy[inner], -radius),
                        (f"{name}: x of column 0", dx[(col == 0) & (row >= 2)], -0.5)):
        bins, expected = _expected_counts(value_at, radius, lo, radius, d.size)
        observed, _ = np.histogram(np.clip(d, bins[0], bins[-1]), bins)
        assert_chi2(observed, expected, what)
    assert x.min() >= 0.0 and x.max() <= cam.width and y.min() >= 0.0 and y.max() <= cam.height


def test_sample_border_lets_positions_leave_the_film():
    cam = _ortho(8, 8, pixel_filter="gaussian", sample_border=True)
    x, _, pixel = _film_positions(cam, 400)
    dx = x - (pixel % cam.width + 0.5)
    assert x.min() < -1.0 and x.max() > cam.width + 1.0
    bins, expected = _expected_counts(lambda v: _mitsuba_gaussian(v, 0.5, 2.0), 2.0, -2.0, 2.0, dx.size)
    observed, _ = np.histogram(np.clip(dx, bins[0], bins[-1]), bins)
    assert_chi2(observed, expected, "gaussian with sample_border")


@nb.njit
def _eye_rays_before_filters(frame, width, seed, iteration, count):
    """`kernels.emit.generate_eye_rays` as it was before cameras had
    filters (main at 401e87f), serial: every ray jittered in its pixel."""
    origin, direction = np.empty((count, 3), np.float32), np.empty((count, 3), np.float32)
    pos, right, up, fwd = frame[0], frame[1], frame[2], frame[3]
    aperture, focus, near = frame[5, 0], frame[5, 1], frame[5, 2]
    job = rng.EYE_STREAM + np.uint64(iteration)
    for i in range(count):
        st = rng.path_state(np.uint64(seed), job, np.uint64(i))
        st, ux = rng.next_float(st)
        st, uy = rng.next_float(st)
        col, row = i % width, i // width
        sx = (2.0 * (col + ux) / width - 1.0) * frame[4, 0]
        sy = (1.0 - 2.0 * (row + uy) / frame[4, 2]) * frame[4, 1]
        d, o = np.empty(3), np.empty(3)
        if frame[6, 0] > 0.0:
            for k in range(3):
                direction[i, k] = fwd[k]
                origin[i, k] = pos[k] + sx * right[k] + sy * up[k] + near * fwd[k]
            continue
        for k in range(3):
            d[k] = fwd[k] + sx * right[k] + sy * up[k]
            o[k] = pos[k]
        if aperture > 0.0:
            st, u1 = rng.next_float(st)
            st, u2 = rng.next_float(st)
            lx, ly = emit.concentric_disk(u1, u2)
            for k in range(3):
                focus_point = pos[k] + d[k] * focus
                o[k] = pos[k] + aperture * (lx * right[k] + ly * up[k])
                d[k] = focus_point - o[k]
        inv = 1.0 / math.sqrt(d[0] * d[0] + d[1] * d[1] + d[2] * d[2])
        cos_f = (d[0] * fwd[0] + d[1] * fwd[1] + d[2] * fwd[2]) * inv
        for k in range(3):
            direction[i, k] = d[k] * inv
            origin[i, k] = o[k] + d[k] * inv * (near / cos_f)
    return origin, direction


@pytest.mark.parametrize("camera", [
    {"projection": "orthographic", "near_clip": 0.2},
    {"near_clip": 0.1},
    {"aperture_radius": 0.05, "focus_distance": 2.0},
])
def test_the_half_pixel_box_makes_the_rays_it_made_before_filters(camera):
    """The box filter of half a pixel (every scene before filters, and any
    that asks for the box) draws the same numbers and makes the same rays,
    bit for bit, so box-filtered renders are unchanged for equal seeds."""
    cam = Camera(position=(0.3, 0.2, 1.0), look_at=(0.0, -0.1, -1.0), up=(0.0, 1.0, 0.0), fov_deg=50.0,
                 width=13, height=9, **camera)
    for iteration in (0, 7):
        origin, direction, _ = emit.generate_eye_rays(cam.frame(), cam.width, np.uint64(9), np.uint64(iteration),
                                                      0, 13 * 9)
        want_origin, want_direction = _eye_rays_before_filters(cam.frame(), cam.width, 9, iteration, 13 * 9)
        assert np.array_equal(origin, want_origin) and np.array_equal(direction, want_direction)


# -- the scene reader and the header -----------------------------------------------------
SCENE = """<scene version="3.0.0">
  <sensor type="perspective"><float name="fov" value="40"/>
    <film type="hdrfilm"><integer name="width" value="16"/><integer name="height" value="12"/>{film}</film>
  </sensor>
  <shape type="rectangle"><emitter type="area"><rgb name="radiance" value="1"/></emitter></shape>
</scene>"""


def _load(tmp_path, film: str):
    path = tmp_path / "scene.xml"
    path.write_text(SCENE.format(film=film))
    return load_mitsuba(str(path))


@pytest.mark.parametrize("film, want", [
    ("", ("gaussian", 2.0, 0.5, False)),
    ('<rfilter type="gaussian"><float name="stddev" value="0.25"/></rfilter>', ("gaussian", 1.0, 0.25, False)),
    ('<rfilter type="box"/>', ("box", 0.5, 0.5, False)),
    ('<rfilter type="tent"><float name="radius" value="1.5"/></rfilter><boolean name="sample_border" value="true"/>',
     ("tent", 1.5, 0.5, True)),
])
def test_the_reader_gives_the_camera_mitsubas_filter(tmp_path, film, want):
    """No <rfilter>: Mitsuba's default Gaussian (stddev 0.5, cut at 4 stddev)."""
    cam = _load(tmp_path, film).camera
    assert (cam.pixel_filter, cam.filter_radius_px(), cam.filter_stddev, cam.sample_border) == want


@pytest.mark.parametrize("film, words", [
    ('<rfilter type="lanczos"/>', "rfilter 'lanczos' is not supported"),
    ('<rfilter type="gaussian"><float name="radius" value="1"/></rfilter>', "unsupported parameter"),
    ('<rfilter type="gaussian"><float name="stddev" value="-1"/></rfilter>', "stddev must lie in"),
])
def test_the_reader_refuses_other_filters_in_one_line(tmp_path, film, words):
    with pytest.raises(SceneError) as err:
        _load(tmp_path, film)
    message = str(err.value)
    assert "\n" not in message and "scene.xml:3:" in message and "<rfilter" in message and words in message


def test_the_filter_travels_with_the_header_to_the_tracers(tmp_path):
    """Tracers make eye rays from the header they are sent: the same rays."""
    scene = _load(tmp_path, '<rfilter type="gaussian"><float name="stddev" value="0.4"/></rfilter>')
    header = SceneHeader.from_wire(scene.header().to_wire())
    assert header.camera == scene.camera
    want, got = eye_ray_job(scene, 5, 2, 0, 16 * 12), eye_ray_job(header, 5, 2, 0, 16 * 12)
    assert np.array_equal(want.direction, got.direction)
    box = eye_ray_job(dataclasses.replace(scene, camera=dataclasses.replace(scene.camera, pixel_filter="box",
                                                                                filter_radius=None)), 5, 2, 0, 192)
    assert not np.array_equal(box.direction, got.direction)


def test_a_bad_filter_on_the_camera_is_a_scene_error():
    for fields in ({"pixel_filter": "mitchell"}, {"pixel_filter": "gaussian", "filter_stddev": 0.0},
                   {"pixel_filter": "box", "filter_radius": 100.0}):
        with pytest.raises(SceneError):
            _ortho(4, 4, **fields).validate()


# -- Mitsuba's own filters ------------------------------------------------------------------
@pytest.mark.reference
@pytest.mark.parametrize("plugin, camera", [
    ({"type": "gaussian"}, {"pixel_filter": "gaussian"}),
    ({"type": "gaussian", "stddev": 0.3}, {"pixel_filter": "gaussian", "filter_stddev": 0.3}),
    ({"type": "tent", "radius": 1.5}, {"pixel_filter": "tent", "filter_radius": 1.5}),
])
def test_our_table_is_mitsubas_discretised_filter(plugin, camera):
    """Mitsuba's film weighs samples with `eval_discretized`; our table is
    that function, step for step (to 0.1% of its peak: Mitsuba evaluates
    exp by a fast approximation)."""
    import mitsuba as mi
    mi.set_variant("scalar_rgb")
    rfilter = mi.load_dict(plugin)
    cam = _ortho(4, 4, **camera)
    radius = cam.filter_radius_px()
    assert rfilter.radius() == pytest.approx(radius, rel=1e-6)
    table = emit.filter_table(cam.frame()[7])
    middles = (np.arange(STEPS) + 0.5) * radius / STEPS
    theirs = np.array([rfilter.eval_discretized(float(x)) for x in middles])
    np.testing.assert_allclose(table / table[0], theirs / theirs[0], rtol=0, atol=1e-3)
    assert rfilter.eval_discretized(float(radius) * 1.001) == 0.0


def test_other_loaders_keep_the_box_and_toml_files_may_choose(tmp_path):
    """Built-in and TOML scenes render as before (the box) unless a TOML
    camera names a filter."""
    from dosppm_core.scene.builtin import cornell_box
    from dosppm_core.scene.tomlfile import load_toml
    from tests.test_scenefile import BASE
    assert cornell_box().camera.pixel_filter == "box"
    path = tmp_path / "scene.toml"
    path.write_text(BASE)
    assert load_toml(str(path)).camera.pixel_filter == "box"
    path.write_text(BASE.replace("height = 24", 'height = 24\npixel_filter = "gaussian"\nfilter_stddev = 0.4'))
    cam = load_toml(str(path)).camera
    assert (cam.pixel_filter, cam.filter_radius_px()) == ("gaussian", pytest.approx(1.6))
    path.write_text(BASE.replace("height = 24", 'height = 24\npixel_filter = "lanczos"'))
    with pytest.raises(SceneError, match="camera.pixel_filter: must be one of box, gaussian, tent"):
        load_toml(str(path))
