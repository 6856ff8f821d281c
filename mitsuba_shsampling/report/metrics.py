"""Image error metrics of a comparison (NumPy, images as (H, W, C) float arrays).

All metrics average over pixels and colour channels. ``passes`` is a
(K, H, W, C) stack of K independent renders of the same method and settings.
"""

from __future__ import annotations

import math

import numpy as np

#: Regulariser of the relative error: (x - ref)^2 / (ref^2 + REL_EPSILON).
REL_EPSILON = 1e-2
#: A pixel (or the image mean) is biased if it is further than this many standard errors away.
BIAS_Z_THRESHOLD = 4.0
#: With K passes the per-pixel standard error is itself estimated from K - 1 degrees of
#: freedom, so for normal pass values |z| follows Student's t and exceeds 4 by chance in a
#: known fraction of pixels (15.6 % for K = 2, 2.8 % for K = 4). A fraction above this factor
#: times that expectation plus this margin is flagged (``pixels_suspect``): local bias, or
#: heavy-tailed pass values (a sun found by rare samples), which K passes cannot tell apart.
BIAS_PIXEL_FACTOR = 1.5
BIAS_PIXEL_MARGIN = 0.01


def mse(image: np.ndarray, reference: np.ndarray) -> float:
    """Mean squared error over pixels and channels."""
    return float(np.mean((image - reference) ** 2))


def rel_mse(image: np.ndarray, reference: np.ndarray) -> float:
    """Relative MSE: mean of (x - ref)^2 / (ref^2 + 1e-2) over pixels and channels."""
    return float(np.mean((image - reference) ** 2 / (reference ** 2 + REL_EPSILON)))


def rel_squared_error_map(passes: np.ndarray, reference: np.ndarray) -> np.ndarray:
    """Per-pixel relative squared error, averaged over passes and channels: (H, W)."""
    return np.mean((passes - reference[None]) ** 2 / (reference[None] ** 2 + REL_EPSILON), axis=(0, 3))


def pixel_variance(passes: np.ndarray) -> np.ndarray:
    """Unbiased variance of one pass across the K passes, channel-averaged: (H, W). Needs K >= 2."""
    if passes.shape[0] < 2:
        raise ValueError("per-pixel variance needs at least 2 passes")
    return np.mean(np.var(passes, axis=0, ddof=1), axis=-1)


def efficiency(mse_value: float, time_s: float) -> float:
    """1 / (MSE x time): higher is better; inf for a zero-error or zero-time render."""
    denom = mse_value * time_s
    return float(1.0 / denom) if denom > 0 else float("inf")


def student_t_tail(threshold: float, dof: int) -> float:
    """P(|T| > threshold) for Student's t with ``dof`` degrees of freedom.

    Integrates the density over [threshold, inf) after substituting t = threshold / u
    (u in (0, 1]), with 256-point Gauss-Legendre quadrature.
    """
    if dof < 1:
        raise ValueError("Student's t needs at least one degree of freedom")
    nodes, weights = np.polynomial.legendre.leggauss(256)
    u = 0.5 * (nodes + 1.0)
    t = threshold / u
    log_norm = math.lgamma((dof + 1) / 2) - math.lgamma(dof / 2) - 0.5 * math.log(dof * math.pi)
    density = np.exp(log_norm - 0.5 * (dof + 1) * np.log1p(t * t / dof))
    return float(2.0 * np.sum(0.5 * weights * density * threshold / (u * u)))


def bias_check(passes: np.ndarray, reference: np.ndarray, reference_variance: np.ndarray) -> dict:
    """Does the mean of the passes agree with the reference within statistical error?

    :param passes: (K, H, W, C) independent renders, K >= 2.
    :param reference: (H, W, C) reference image.
    :param reference_variance: (H, W, C) variance of the reference estimate itself
        (zeros if unknown).
    :returns: ``fail_fraction`` (pixel-channels with |z| > 4), ``expected_fail_fraction``
        (the same under no bias, from Student's t with K - 1 degrees of freedom),
        ``pixels_suspect`` (the fraction clearly above that), ``mean_z`` (z-score of the
        image-mean difference, pixels treated as independent) and ``bias_ok`` (|mean_z| <= 4).

    ``bias_ok`` rests on the image mean because its standard error pools every pixel's
    variance (many degrees of freedom, close to normal by the central limit theorem), while
    per-pixel statistics of estimators with rare, very bright samples (a sun found only by
    BSDF sampling) are far from normal at low spp and flag unbiased methods too.
    """
    k = passes.shape[0]
    if k < 2:
        raise ValueError("the bias check needs at least 2 passes")
    diff = passes.mean(axis=0) - reference
    var_of_mean = passes.var(axis=0, ddof=1) / k + reference_variance
    se = np.sqrt(var_of_mean)
    with np.errstate(divide="ignore", invalid="ignore"):
        z = np.where(se > 0, np.abs(diff) / se, np.where(np.abs(diff) > 0, np.inf, 0.0))
    fail_fraction = float(np.mean(z > BIAS_Z_THRESHOLD))
    n = diff.size
    mean_se = float(np.sqrt(var_of_mean.sum()) / n)
    mean_diff = float(diff.mean())
    mean_z = mean_diff / mean_se if mean_se > 0 else (0.0 if mean_diff == 0 else float("inf"))
    expected = student_t_tail(BIAS_Z_THRESHOLD, k - 1)
    return {
        "fail_fraction": fail_fraction,
        "expected_fail_fraction": expected,
        "pixels_suspect": bool(fail_fraction > BIAS_PIXEL_FACTOR * expected + BIAS_PIXEL_MARGIN),
        "mean_z": float(mean_z),
        "bias_ok": bool(abs(mean_z) <= BIAS_Z_THRESHOLD),
    }
