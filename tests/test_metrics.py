"""Error metrics on arrays with known answers, and `dosppm compare`."""
import json
import sys

import numpy as np
import pytest

from dosppm_core.film import write_exr
from harness import metrics
from services.cli.main import main as dosppm_main

RNG = np.random.default_rng(7)


def _image(h=16, w=20):
    return RNG.random((h, w, 3)) + 0.1


def test_rmse_of_constant_offset():
    ref = _image()
    assert metrics.rmse(ref + 0.25, ref) == pytest.approx(0.25)
    assert metrics.rmse(ref, ref) == 0.0


def test_relmse_of_scaled_image_matches_closed_form():
    ref = _image()
    k, eps = 1.1, 1e-2
    # (k ref - ref)^2 / (ref^2 + eps) = (k - 1)^2 ref^2 / (ref^2 + eps)
    expected = np.mean((k - 1) ** 2 * ref ** 2 / (ref ** 2 + eps))
    assert metrics.relmse(k * ref, ref, eps) == pytest.approx(expected, rel=1e-12)
    assert metrics.relmse(k * ref, ref, eps=0.0) == pytest.approx((k - 1) ** 2)


def test_seed_noise_is_the_relmse_one_render_has_from_its_noise():
    """Two independent renders, each truth + noise of known relative
    variance: seed_noise recovers it, where relmse(a, b) / 2 does not when
    the noise is heavy-tailed (a rare bright path that one seed found)."""
    rng = np.random.default_rng(5)
    truth = np.full((200, 200, 3), 2.0)
    sigma = 0.1 * truth
    a, b = (truth + rng.normal(0.0, 1.0, truth.shape) * sigma for _ in range(2))
    expected = float(np.mean(sigma ** 2 / (truth ** 2 + 1e-2)))
    assert metrics.seed_noise(a, b) == pytest.approx(expected, rel=0.03)
    # a rare path: one pixel of 40,000 is 1,000x brighter in one seed (and black
    # in the other); it adds its own (a - b)^2 / (2 m^2) = 2000^2 / (2 * 1000^2) = 2,
    # over 40,000 pixels
    a2, b2 = a.copy(), b.copy()
    a2[7, 7], b2[7, 7] = 2000.0, 0.0
    assert metrics.seed_noise(a2, b2) - metrics.seed_noise(a, b) == pytest.approx(2.0 / 40_000, rel=0.01)
    assert metrics.relmse(a2, b2) / 2 > 1000 * metrics.seed_noise(a2, b2)


def test_mean_luminance_bias_of_scaled_and_grey_images():
    ref = _image()
    assert metrics.mean_luminance_bias(1.03 * ref, ref) == pytest.approx(0.03)
    grey = np.full((2, 2, 3), 0.5)
    green_only = np.zeros((2, 2, 3))
    green_only[..., 1] = 0.5
    # Luminance of pure green is 0.7152 of grey's.
    assert metrics.mean_luminance_bias(green_only, grey) == pytest.approx(0.7152 - 1)
    with pytest.raises(ValueError, match="zero mean luminance"):
        metrics.mean_luminance_bias(grey, np.zeros_like(grey))


def test_blurred_relmse_separates_noise_from_bias():
    ref = np.full((64, 64, 3), 0.5)
    noise = RNG.normal(0, 0.05, ref.shape)
    noisy, biased = ref + noise, ref * 1.05
    # Blurring removes most of the noise but none of the bias.
    assert metrics.blurred_relmse(noisy, ref, 3.0) < 0.05 * metrics.relmse(noisy, ref)
    assert metrics.blurred_relmse(biased, ref, 3.0) == pytest.approx(metrics.relmse(biased, ref))
    assert metrics.blurred_relmse(noisy, ref, 0.0) == metrics.relmse(noisy, ref)


def test_blurred_relmse_over_a_mask_ignores_the_pixels_outside_it():
    """A mirror the reference renders differently (unscored) must not leak
    its error into the scored pixels beside it through the blur."""
    ref = np.full((32, 32, 3), 0.5)
    img = ref.copy()
    img[:, 14:18] = 5.0                               # the unscored stripe: far off
    where = np.ones((32, 32), bool)
    where[:, 14:18] = False
    assert metrics.blurred_relmse(img, ref, 2.0, where=where) == pytest.approx(0.0, abs=1e-20)
    biased = ref * 1.05
    biased[:, 14:18] = 5.0
    assert metrics.blurred_relmse(biased, ref, 2.0, where=where) == pytest.approx(
        metrics.relmse(biased[where], ref[where]))


def test_gaussian_blur_preserves_constants_and_mass():
    img = np.zeros((31, 33, 3))
    img[15, 16] = 1.0
    out = metrics.gaussian_blur(img, 2.0)
    assert out.sum() == pytest.approx(3.0)           # impulse far from the edges
    assert out[15, 16, 0] == out.max()
    np.testing.assert_allclose(metrics.gaussian_blur(np.full((3, 2, 3), 0.7), 5.0), 0.7)


def test_tile_means():
    img = np.arange(24, dtype=float).reshape(4, 6)
    np.testing.assert_allclose(metrics.tile_means(img, (2, 3)),
                               [[3.5, 5.5, 7.5], [15.5, 17.5, 19.5]])
    rgb = np.stack([img, 2 * img, 3 * img], axis=-1)
    assert metrics.tile_means(rgb, 2).shape == (2, 2, 3)
    np.testing.assert_allclose(metrics.tile_means(rgb, 1)[0, 0], [11.5, 23.0, 34.5])
    with pytest.raises(ValueError, match="tiles"):
        metrics.tile_means(img, (5, 1))


@pytest.mark.parametrize("bad", [np.nan, np.inf, -np.inf])
def test_nan_and_inf_are_rejected(bad):
    ref = _image()
    a = ref.copy()
    a[3, 4, 1] = bad
    for fn in (metrics.rmse, metrics.relmse, metrics.mean_luminance_bias):
        with pytest.raises(ValueError, match="NaN or Inf"):
            fn(a, ref)
    with pytest.raises(ValueError, match="ref contains NaN or Inf"):
        metrics.relmse(ref, a)
    with pytest.raises(ValueError, match="NaN or Inf"):
        metrics.blurred_relmse(a, ref, 1.0)


def test_shape_mismatch_rejected():
    with pytest.raises(ValueError, match="shape mismatch"):
        metrics.rmse(np.zeros((2, 2, 3)), np.zeros((2, 3, 3)))


def test_difference_png_colours(tmp_path):
    ref = np.full((4, 6, 3), 0.5)
    a = ref.copy()
    a[:, :2] *= 0.5     # darker: blue
    a[:, 4:] *= 1.5     # brighter: red
    path = tmp_path / "diff.png"
    scale = metrics.difference_png(str(path), a, ref, scale=1.0)
    assert scale == 1.0
    mpl_image = pytest.importorskip("matplotlib.image")
    px = np.round(mpl_image.imread(str(path)) * 255).astype(int)
    assert px.shape == (4, 6, 3)
    blue, white, red = px[0, 0], px[0, 3], px[0, 5]
    assert blue[2] > blue[0] + 50 and red[0] > red[2] + 50
    assert white.min() >= 250


@pytest.mark.parametrize("with_matplotlib", [True, False])
def test_diverging_ramp_is_blue_white_red(monkeypatch, with_matplotlib):
    if not with_matplotlib:
        monkeypatch.setitem(sys.modules, "matplotlib", None)   # forces the built-in ramp
    colours = metrics._diverging_colours(np.array([-1.0, 0.0, 1.0])).astype(int)
    assert colours[1].min() >= 254                              # white (bwr's LUT: 254)
    assert colours[0, 2] == 255 and colours[0, 0] < 10          # blue
    assert colours[2, 0] == 255 and colours[2, 2] < 10          # red


# -- dosppm compare ---------------------------------------------------------
def _run_compare(argv):
    return dosppm_main(["compare", *argv])


def test_compare_prints_metrics_and_json(tmp_path, capsys):
    ref = _image(8, 10)
    a_path, b_path = str(tmp_path / "a.exr"), str(tmp_path / "b.exr")
    write_exr(a_path, 1.1 * ref)
    write_exr(b_path, ref)
    assert _run_compare([a_path, b_path, "--diff", str(tmp_path / "d.png")]) == 0
    lines = dict(line.split() for line in capsys.readouterr().out.splitlines())
    assert set(lines) >= {"rmse", "relmse", "mean_luminance_bias"}
    assert float(lines["mean_luminance_bias"]) == pytest.approx(0.1, rel=1e-4)
    assert (tmp_path / "d.png").exists()
    assert _run_compare([a_path, b_path, "--json"]) == 0
    record = json.loads(capsys.readouterr().out)
    assert record["relmse"] == pytest.approx(metrics.relmse(1.1 * ref.astype(np.float32),
                                                            ref.astype(np.float32)), rel=1e-5)


def test_compare_bad_inputs_exit_2_with_one_line(tmp_path, capsys):
    good = str(tmp_path / "good.exr")
    write_exr(good, np.ones((4, 4, 3)))
    small = str(tmp_path / "small.exr")
    write_exr(small, np.ones((2, 4, 3)))
    nan = str(tmp_path / "nan.exr")
    write_exr(nan, np.full((4, 4, 3), np.nan))
    cases = [(str(tmp_path / "none.exr"), "none.exr"), (small, "small.exr"), (nan, "nan.exr")]
    for path, name in cases:
        assert _run_compare([path, good]) == 2
        err = capsys.readouterr().err
        assert name in err and err.count("\n") == 1
