"""Scoring a render against a Mitsuba 3 render-test reference, as strictly
as Mitsuba's own test (its src/render/tests/test_renders.py).

Mitsuba renders a test scene once and takes the reference's per-sample
variance image, over its own sample count, as the variance of its mean.
SPPM has no per-sample variance (its pixels average photons over a
shrinking radius), so our mean and the variance of that mean come from K
independent seeds (K >= `MIN_SEEDS`), and the reference's own noise
(per-sample variance over `REFERENCE_SPP`) is added:

    z = (mean_k ours_k - ref) / sqrt(max(var_k(ours_k) / K + max(ref_var, 1e-4) / 32000, 1e-4 / spp))

per pixel channel, spp being the samples per pixel Mitsuba's test renders
at (2e6 over the image's pixels): 1e-4 / spp is Mitsuba's floor on the
variance of the tested mean. What follows is Mitsuba's, step by step: every image
(ours, the reference, its variance image) is converted from linear sRGB
to XYZ with Mitsuba's matrix before the test; the reference variance is
floored at 1e-4; the test is two-sided at significance 0.01 with the
Šidák correction over the pixels, alpha = 1 - (1 - 0.01)^(1/pixels); a
channel passes when its p-value exceeds alpha (a NaN fails); the scene
passes when passing channels / 3 >= 99.75% of the pixels.

One departure, forced by the estimated variance: with K seeds the
variance of our mean is itself a random estimate (K - 1 degrees of
freedom), so z follows Student's t, not the normal: at K = 4 a normal
threshold (4.6 sigma at 48x48) would fail about 2% of channels of a
perfectly unbiased render. The p-value is Student's t with K - 1 degrees
of freedom (`p_values` says where not).

Where all K seeds agree exactly (a white background, an emitter seen
directly, a direct-only scene's exact shading) we have no estimate of our
variance, and there Mitsuba's own model judges: max(ref_var, 1e-4) / spp,
the reference's per-sample variance over the test render's samples (or
the reference's own noise, if larger). A
reference whose spectral variant is off the RGB answer by a few of its
own standard errors would otherwise fail a render that is exactly right,
which Mitsuba's test passes: in projector_constant's lit square we (and
Mitsuba's scalar_rgb) give 1, the reference 0.9975 in G with a per-sample
variance of 0.0025, judged by Mitsuba's test on sqrt(0.0025 / 868) =
0.0017 (z 1.5) and by a zero variance on the floor, 0.00034 (z 7).
Wherever our seeds vary, their variance judges, stricter than Mitsuba's
test (which takes the reference's per-sample variance for the render's). On top, issue 33 bounds the bias of the mean:
|mean Y(ours) - mean Y(ref)| / mean Y(ref) <= 1%, Y the luminance.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from harness.metrics import luminance

SIGNIFICANCE = 0.01
PASS_FRACTION = 0.9975
REFERENCE_SPP = 32_000
VARIANCE_FLOOR = 1e-4          # Mitsuba's floor on the reference's per-sample variance
SAMPLE_BUDGET = 2_000_000       # Mitsuba's test renders 2e6 samples over the image
MIN_SEEDS = 4
BIAS_BOUND = 0.01
# Mitsuba's linear sRGB -> XYZ (src/core/color.h, srgb_to_xyz), as its
# Bitmap.convert applies it to the reference, its variance image and the render.
SRGB_TO_XYZ = np.array([[0.412453, 0.357580, 0.180423],
                        [0.212671, 0.715160, 0.072169],
                        [0.019334, 0.119193, 0.950227]])


@dataclass(frozen=True)
class Score:
    """The verdict on one scene: `passed` when both the z-test
    (`z_pass_fraction` >= `PASS_FRACTION`) and the bias bound hold."""
    passed: bool
    z_pass_fraction: float      # passing channels / 3 / pixels, as Mitsuba counts
    bias: float                 # (mean Y(ours) - mean Y(ref)) / mean Y(ref)
    seeds: int
    pixels: int
    alpha: float                # the Šidák-corrected per-pixel significance
    min_p: float

    @property
    def z_passed(self) -> bool:
        return self.z_pass_fraction >= PASS_FRACTION

    def as_dict(self) -> dict:
        return {"passed": self.passed, "z_pass_fraction": self.z_pass_fraction, "bias": self.bias,
                "seeds": self.seeds, "pixels": self.pixels, "alpha": self.alpha, "min_p": self.min_p}


def score(renders, reference, reference_var, reference_spp: int = REFERENCE_SPP) -> Score:
    """Score `renders`, K >= MIN_SEEDS linear-sRGB (H, W, 3) images of one
    scene at independent seeds, against Mitsuba's `reference` and its
    per-sample variance image `reference_var` (both linear sRGB, as the
    test's `_ref_rgb.exr` and `_ref_rgb_var.exr`)."""
    ours = np.asarray([np.asarray(r, np.float64) for r in renders]) if len(renders) else np.zeros((0,))
    ref, ref_var = np.asarray(reference, np.float64), np.asarray(reference_var, np.float64)
    if len(ours) < MIN_SEEDS:
        raise ValueError(f"{len(ours)} renders: the variance of our mean needs at least {MIN_SEEDS} "
                         f"independent seeds")
    if ref.ndim != 3 or ref.shape[2] != 3 or ours.shape[1:] != ref.shape or ref_var.shape != ref.shape:
        raise ValueError(f"shapes differ: renders {ours.shape[1:]}, reference {ref.shape}, "
                         f"variance {ref_var.shape} (each (H, W, 3))")
    k, pixels = len(ours), ref.shape[0] * ref.shape[1]
    p = p_values(ours @ SRGB_TO_XYZ.T, ref @ SRGB_TO_XYZ.T, ref_var @ SRGB_TO_XYZ.T, reference_spp,
                 mitsuba_spp(pixels))
    alpha = 1.0 - (1.0 - SIGNIFICANCE) ** (1.0 / pixels)
    fraction = float(np.count_nonzero(p > alpha)) / 3 / pixels
    bias = mean_bias(ours.mean(axis=0), ref)
    passed = fraction >= PASS_FRACTION and abs(bias) <= BIAS_BOUND
    return Score(bool(passed), fraction, bias, k, pixels, alpha, float(np.nanmin(p)) if np.any(p == p) else math.nan)


def mitsuba_spp(pixels: int) -> int:
    """The samples per pixel of Mitsuba's test render of an image of `pixels`."""
    return max(1, SAMPLE_BUDGET // pixels)


def p_values(ours_xyz: np.ndarray, ref_xyz: np.ndarray, ref_var_xyz: np.ndarray,
             reference_spp: int = REFERENCE_SPP, spp: int | None = None) -> np.ndarray:
    """Two-sided p-values per pixel channel of the K renders `ours_xyz`
    (K, H, W, 3) against the reference (see the module doc); `spp`, that
    of Mitsuba's test render, by default `mitsuba_spp` of the image's pixels."""
    k = ours_xyz.shape[0]
    spp = mitsuba_spp(ref_xyz.shape[0] * ref_xyz.shape[1]) if spp is None else spp
    # Seeds that agree exactly have no variance; `var` could leave a
    # rounding residue of their mean (it does for 16 equal values, not for 4).
    agree = np.all(ours_xyz == ours_xyz[:1], axis=0)
    var_ours = np.where(agree, 0.0, ours_xyz.var(axis=0, ddof=1) / k)
    var_ref = np.maximum(ref_var_xyz, VARIANCE_FLOOR) / reference_spp
    var = np.maximum(var_ours + var_ref, VARIANCE_FLOOR / spp)
    # No estimate of ours: Mitsuba's model of its own render (module doc).
    var = np.where(agree, np.maximum(var, np.maximum(ref_var_xyz, VARIANCE_FLOOR) / spp), var)
    with np.errstate(invalid="ignore", divide="ignore"):
        z = (ours_xyz.mean(axis=0) - ref_xyz) / np.sqrt(var)
    # Student's t with K - 1 degrees of freedom: exact when the reference's
    # noise is negligible, conservative otherwise (the textbook lower bound
    # of Welch's). Welch and Satterthwaite's estimate of them was tried and
    # failed unbiased renders: where four seeds happen to agree closely it
    # grows large and takes the normal's tail. Pixels whose seeds agree
    # exactly (black, an emitter seen directly) carry no estimate: the
    # reference's noise alone, nearly normal. A floored variance keeps
    # Student's t: it is max(our estimate, floor), the estimate still random.
    dof = np.where(var_ours > 0, k - 1.0, reference_spp - 1.0)
    return student_t_two_sided(z, dof)


def mean_bias(ours_rgb: np.ndarray, ref_rgb: np.ndarray) -> float:
    """(mean Y(ours) - mean Y(ref)) / mean Y(ref); NaN when ours has NaN."""
    y_ref = float(np.mean(luminance(ref_rgb)))
    if y_ref <= 0:
        return math.inf
    return (float(np.mean(luminance(ours_rgb))) - y_ref) / y_ref


# -- Student's t without scipy --------------------------------------------------------
NORMAL_BEYOND_DOF = 1e5     # the t and the normal tails agree to 1e-4 relative there


def student_t_two_sided(t: np.ndarray, dof: np.ndarray) -> np.ndarray:
    """P(|T| >= |t|) for Student's t with `dof` degrees of freedom (arrays,
    broadcast): the regularized incomplete beta I_x(dof/2, 1/2) at
    x = dof / (dof + t^2); the normal's erfc beyond `NORMAL_BEYOND_DOF`.
    NaN in, NaN out."""
    t, dof = np.broadcast_arrays(np.abs(np.asarray(t, np.float64)), np.asarray(dof, np.float64))
    out = np.full(t.shape, np.nan)
    normal = np.isfinite(t) & (dof >= NORMAL_BEYOND_DOF)
    out[normal] = _erfc(t[normal] / math.sqrt(2.0))
    small = np.isfinite(t) & (dof > 0) & (dof < NORMAL_BEYOND_DOF)
    a = dof[small] / 2.0
    x = dof[small] / (dof[small] + t[small] ** 2)
    out[small] = incomplete_beta(a, np.full_like(a, 0.5), x)
    out[np.isinf(t)] = 0.0
    return out


_erfc = np.vectorize(math.erfc, otypes=[np.float64])
_lgamma = np.vectorize(math.lgamma, otypes=[np.float64])


def incomplete_beta(a: np.ndarray, b: np.ndarray, x: np.ndarray, iterations: int = 400) -> np.ndarray:
    """The regularized incomplete beta I_x(a, b), vectorised: Lentz's
    continued fraction, on the side of x where it converges fast
    (I_x(a, b) = 1 - I_{1-x}(b, a))."""
    a, b, x = (np.asarray(v, np.float64) for v in (a, b, x))
    flip = x > (a + 1.0) / (a + b + 2.0)
    a2, b2, x2 = np.where(flip, b, a), np.where(flip, a, b), np.where(flip, 1.0 - x, x)
    with np.errstate(divide="ignore"):
        log_front = (_lgamma(a2 + b2) - _lgamma(a2) - _lgamma(b2)
                     + a2 * np.log(x2) + b2 * np.log1p(-x2)) if a2.size else a2
    value = np.exp(log_front) * _beta_fraction(a2, b2, x2, iterations) / a2
    value = np.where(flip, 1.0 - value, value)
    return np.where(x <= 0.0, 0.0, np.where(x >= 1.0, 1.0, value))


def _beta_fraction(a, b, x, iterations):
    tiny = 1e-300
    c, d = np.ones_like(x), 1.0 - (a + b) * x / (a + 1.0)
    d = 1.0 / np.where(np.abs(d) < tiny, tiny, d)
    h = d.copy()
    for m in range(1, iterations + 1):
        for num in (m * (b - m) * x / ((a + 2 * m - 1) * (a + 2 * m)),
                    -(a + m) * (a + b + m) * x / ((a + 2 * m) * (a + 2 * m + 1))):
            d = 1.0 + num * d
            d = 1.0 / np.where(np.abs(d) < tiny, tiny, d)
            c = 1.0 + num / c
            c = np.where(np.abs(c) < tiny, tiny, c)
            h = h * d * c
        if np.all(np.abs(d * c - 1.0) < 1e-12):
            break
    return h
