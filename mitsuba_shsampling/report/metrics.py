"""Error statistics of a comparison (NumPy; images are (H, W, C) float arrays).

``passes`` is always a (K, H, W, C) stack of K independent renders of one
method at one setting. Three kinds of statistics, one dataclass each:

- :class:`ErrorStats`, the *expected* error: each pass's MSE averaged over many
  passes (rare, huge samples included once K is large enough to see them), and
  the per-pixel variance across passes beside it.
- :class:`TailStats`, what an average hides: the brightest pixel, a high
  percentile of the per-pixel luminance error, and a firefly count.
- :class:`BiasTest`, a t-test of the per-pass image-mean luminance against the
  reference's. One number per pass, so the colour channels (strongly correlated
  in every render) are never treated as independent.

Every interval of a ratio between two methods (the verdict's, the per-material
breakdown's) is the paired bootstrap over passes of :func:`paired_bootstrap`.

Non-finite pixel values (a NaN texel, a 0/0 in a plugin) are excluded from
every statistic and counted in ``ErrorStats.non_finite``: a report never shows a
``nan`` without saying where it came from.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Callable

import numpy as np

#: Regulariser of the relative error: (x - ref)^2 / (ref^2 + REL_EPSILON).
REL_EPSILON = 1e-2
#: Rec. 709 luminance weights, those of ``mi.luminance``.
LUMINANCE_WEIGHTS = np.array([0.212671, 0.715160, 0.072169])
#: Tail percentile of |lum(pass) - lum(reference)| over every pixel of every pass.
TAIL_PERCENTILE = 99.99
#: A firefly is a pixel whose luminance exceeds FIREFLY_FACTOR x its reference luminance
#: plus FIREFLY_FLOOR x the reference's image-mean luminance (the floor keeps dark pixels,
#: whose reference is ~0, from counting ordinary noise).
FIREFLY_FACTOR = 10.0
FIREFLY_FLOOR = 1.0
#: Two-sided false-alarm rate of the bias test: an unbiased method is flagged this often.
#: A report holds tens of tests (methods x samplers x equal spp/time), so 1e-3 keeps a
#: false flag rare across a whole report.
BIAS_ALPHA = 1e-3
#: Bootstrap resamples and the two-sided coverage of every interval of a ratio.
BOOTSTRAP_RESAMPLES = 2000
INTERVAL = 0.90


def luminance(images: np.ndarray) -> np.ndarray:
    """Rec. 709 luminance of (..., C) images (C >= 3; a single channel is its own luminance)."""
    if images.shape[-1] < 3:
        return images[..., 0]
    return images[..., :3] @ LUMINANCE_WEIGHTS


def mse(image: np.ndarray, reference: np.ndarray) -> float:
    """Mean squared error over the finite pixels and channels (NaN if none is finite)."""
    return _finite_mean((image - reference) ** 2)


def rel_mse(image: np.ndarray, reference: np.ndarray) -> float:
    """Relative MSE: mean of (x - ref)^2 / (ref^2 + 1e-2) over the finite pixels and channels."""
    return _finite_mean((image - reference) ** 2 / (reference ** 2 + REL_EPSILON))


def rel_squared_error_map(passes: np.ndarray, reference: np.ndarray) -> np.ndarray:
    """Per-pixel relative squared error, averaged over passes and channels: (H, W)."""
    err = _finite_or_nan((passes - reference[None]) ** 2 / (reference[None] ** 2 + REL_EPSILON))
    return _nanmean_or_zero(err, axis=(0, 3))


def pixel_variance(passes: np.ndarray) -> np.ndarray:
    """Unbiased variance of one pass across the K passes, channel-averaged: (H, W). Needs K >= 2."""
    if passes.shape[0] < 2:
        raise ValueError("per-pixel variance needs at least 2 passes")
    with np.errstate(invalid="ignore"):
        var = np.var(_finite_or_nan(passes), axis=0, ddof=1)
    return _nanmean_or_zero(var, axis=-1)


def efficiency(mse_value: float, time_s: float) -> float:
    """1 / (MSE x time): higher is better; inf for a zero-error or zero-time render."""
    denom = mse_value * time_s
    return float(1.0 / denom) if denom > 0 else float("inf")


def paired_bootstrap(ratio: Callable[[np.ndarray], float], passes: int, seed: int = 0) -> tuple[float, float]:
    """The :data:`INTERVAL` bootstrap interval of a ratio between two methods' statistics over
    their ``passes`` passes; ``ratio(idx)`` is the ratio on the passes of index array ``idx``.

    Paired: pass k of both methods is resampled together (the passes are i.i.d. across k; the
    methods share seeds, so pairing also keeps their correlation). (NaN, NaN) if any
    resampled ratio is not finite."""
    rng = np.random.default_rng(seed)
    idx = rng.integers(0, passes, size=(BOOTSTRAP_RESAMPLES, passes))
    ratios = np.array([ratio(i) for i in idx])
    if not np.all(np.isfinite(ratios)):
        return math.nan, math.nan
    tail = (1 - INTERVAL) / 2
    return float(np.quantile(ratios, tail)), float(np.quantile(ratios, 1 - tail))


@dataclasses.dataclass
class ErrorStats:
    """Expected error of one method over K passes.

    :param mse: expected MSE, the mean over passes of each pass's MSE (per channel averaged).
    :param mse_per_pass: the K per-pass MSEs (their spread gives the MSE's uncertainty).
    :param rel_mse: the same for the relative MSE.
    :param pixel_variance: per-pixel variance of one pass across the K passes, mean over the
        image; with the reference noise and the squared bias it makes up the MSE.
    :param non_finite: pixel-channel values that were NaN or infinite (excluded above).
    """

    mse: float
    mse_per_pass: list[float]
    rel_mse: float
    pixel_variance: float
    non_finite: int


def error_stats(passes: np.ndarray, reference: np.ndarray) -> ErrorStats:
    """:class:`ErrorStats` of ``passes`` (K, H, W, C) against ``reference`` (H, W, C)."""
    per_pass = [mse(p, reference) for p in passes]
    return ErrorStats(mse=float(np.mean(per_pass)), mse_per_pass=per_pass,
                      rel_mse=float(np.mean([rel_mse(p, reference) for p in passes])),
                      pixel_variance=float(pixel_variance(passes).mean()),
                      non_finite=int(np.count_nonzero(~np.isfinite(passes))))


@dataclasses.dataclass
class TailStats:
    """The heavy tail of one method's pixel values over K passes (luminance).

    :param max_pixel: the brightest pixel of any pass.
    :param reference_max_pixel: the brightest pixel of the reference, for scale.
    :param abs_error_percentile: the :data:`TAIL_PERCENTILE` percentile of
        |lum(pass) - lum(reference)| over every pixel of every pass.
    :param fireflies: pixels (over all passes) above FIREFLY_FACTOR x reference + FIREFLY_FLOOR x
        the reference's mean luminance.
    :param pixels: pixels examined (K x H x W), the denominator of ``fireflies``.
    """

    max_pixel: float
    reference_max_pixel: float
    abs_error_percentile: float
    fireflies: int
    pixels: int


def tail_stats(passes: np.ndarray, reference: np.ndarray) -> TailStats:
    """:class:`TailStats` of ``passes`` (K, H, W, C) against ``reference`` (H, W, C)."""
    lum = luminance(passes)
    ref = luminance(reference)
    finite = np.isfinite(lum) & np.isfinite(ref)[None]
    abs_err = np.abs(lum - ref[None])[finite]
    threshold = FIREFLY_FACTOR * ref[None] + FIREFLY_FLOOR * float(np.nanmean(_finite_or_nan(ref)))
    return TailStats(
        max_pixel=float(lum[finite].max()) if finite.any() else 0.0,
        reference_max_pixel=float(np.nanmax(_finite_or_nan(ref))) if np.isfinite(ref).any() else 0.0,
        abs_error_percentile=float(np.percentile(abs_err, TAIL_PERCENTILE)) if abs_err.size else 0.0,
        fireflies=int(np.count_nonzero(finite & (lum > threshold))),
        pixels=int(lum.size))


#: A tail is worse than ``direct``'s when its brightest pixel exceeds 3x ``direct``'s (the
#: heavy-tail target of evaluation.md), its error percentile exceeds 1.5x ``direct``'s (more
#: than the scatter of a 99.99 % quantile of ~1e5 values), or its firefly count exceeds
#: ``direct``'s by more than 3 Poisson standard deviations.
TAIL_MAX_RATIO = 3.0
TAIL_PERCENTILE_RATIO = 1.5
TAIL_FIREFLY_SIGMAS = 3.0


def tail_worse(tail: TailStats, baseline: TailStats, baseline_name: str = "direct") -> list[str]:
    """Which tail statistics of ``tail`` are worse than ``baseline``'s (empty: none)."""
    worse = []
    if tail.max_pixel > TAIL_MAX_RATIO * baseline.max_pixel:
        worse.append(f"brightest pixel {tail.max_pixel:.3g} > {TAIL_MAX_RATIO:g} x {baseline_name}'s "
                     f"{baseline.max_pixel:.3g}")
    if tail.abs_error_percentile > TAIL_PERCENTILE_RATIO * baseline.abs_error_percentile:
        worse.append(f"{TAIL_PERCENTILE:g} % error percentile {tail.abs_error_percentile:.3g} > "
                     f"{TAIL_PERCENTILE_RATIO:g} x {baseline_name}'s {baseline.abs_error_percentile:.3g}")
    if tail.fireflies > baseline.fireflies + TAIL_FIREFLY_SIGMAS * math.sqrt(baseline.fireflies + 1):
        worse.append(f"{tail.fireflies} fireflies against {baseline_name}'s {baseline.fireflies}")
    return worse


_GAUSS_LEGENDRE_256 = np.polynomial.legendre.leggauss(256)


def student_t_tail(threshold: float, dof: float) -> float:
    """P(|T| > threshold) for Student's t with ``dof`` (> 0, not necessarily integer) degrees of freedom.

    Integrates the density over [threshold, inf) after substituting t = threshold / u
    (u in (0, 1]), with 256-point Gauss-Legendre quadrature.
    """
    if dof <= 0:
        raise ValueError("Student's t needs a positive number of degrees of freedom")
    if threshold <= 0:
        return 1.0
    nodes, weights = _GAUSS_LEGENDRE_256
    u = 0.5 * (nodes + 1.0)
    t = threshold / u
    log_norm = math.lgamma((dof + 1) / 2) - math.lgamma(dof / 2) - 0.5 * math.log(dof * math.pi)
    density = np.exp(log_norm - 0.5 * (dof + 1) * np.log1p(t * t / dof))
    return float(min(1.0, 2.0 * np.sum(0.5 * weights * density * threshold / (u * u))))


@dataclasses.dataclass
class BiasTest:
    """Welch t-test of the per-pass image-mean luminance against the reference's.

    :param mean: mean over the K passes of each pass's image-mean luminance.
    :param reference_mean: the reference's image-mean luminance (mean over its chunks).
    :param standard_error: of ``mean - reference_mean``, from the spread of the pass means and of
        the reference's chunk means (the reference's own error counts).
    :param t: (mean - reference_mean) / standard_error.
    :param dof: Welch-Satterthwaite degrees of freedom of ``t``.
    :param p_value: two-sided, from Student's t with ``dof`` degrees of freedom.
    :param alpha: the test's false-alarm rate; ``flagged`` iff ``p_value < alpha``.
    """

    mean: float
    reference_mean: float
    standard_error: float
    t: float
    dof: float
    p_value: float
    alpha: float
    flagged: bool


def image_mean_luminance(images: np.ndarray) -> np.ndarray:
    """Image-mean luminance of each image of a (K, H, W, C) stack over its finite pixels: (K,)."""
    lum = _finite_or_nan(luminance(images))
    return np.nanmean(lum.reshape(lum.shape[0], -1), axis=1)


def bias_test(pass_means: np.ndarray, reference_means: np.ndarray, alpha: float = BIAS_ALPHA) -> BiasTest:
    """Is the expectation of a method's pass mean that of the reference?

    :param pass_means: (K,) image-mean luminance of K >= 2 independent passes.
    :param reference_means: (C,) image-mean luminance of C >= 2 independent reference chunks
        (or passes) whose average is the reference; their spread is the reference's own error.
    :param alpha: two-sided false-alarm rate.

    Each pass mean averages every sample of the pass, so it is close to normal even when pixel
    values are heavy-tailed; the spread of the K pass means is the honest standard error,
    whatever the correlation between pixels and channels.
    """
    pass_means = np.asarray(pass_means, dtype=np.float64)
    reference_means = np.asarray(reference_means, dtype=np.float64)
    k, c = pass_means.size, reference_means.size
    if k < 2 or c < 2:
        raise ValueError("the bias test needs at least 2 passes and 2 reference chunks")
    var_p = pass_means.var(ddof=1) / k
    var_r = reference_means.var(ddof=1) / c
    se = math.sqrt(var_p + var_r)
    diff = float(pass_means.mean() - reference_means.mean())
    if se > 0:
        t = diff / se
        dof = (var_p + var_r) ** 2 / (var_p ** 2 / (k - 1) + var_r ** 2 / (c - 1))
        p = student_t_tail(abs(t), dof)
    else:  # every pass and chunk equal (e.g. a black image): any difference is bias
        t, dof, p = (0.0, float(k + c - 2), 1.0) if diff == 0 else (math.copysign(math.inf, diff), float(k + c - 2), 0.0)
    return BiasTest(mean=float(pass_means.mean()), reference_mean=float(reference_means.mean()),
                    standard_error=se, t=float(t), dof=float(dof), p_value=float(p), alpha=alpha,
                    flagged=bool(p < alpha))


def _finite_mean(values: np.ndarray) -> float:
    finite = np.isfinite(values)
    return float(values[finite].mean()) if finite.any() else math.nan


def _finite_or_nan(values: np.ndarray) -> np.ndarray:
    return np.where(np.isfinite(values), values, np.nan)


def _nanmean_or_zero(values: np.ndarray, axis) -> np.ndarray:
    """nanmean that gives 0 (not a warning and NaN) where every value is non-finite."""
    finite = np.isfinite(values)
    count = finite.sum(axis=axis)
    total = np.where(finite, values, 0.0).sum(axis=axis)
    return np.where(count > 0, total / np.maximum(count, 1), 0.0)
