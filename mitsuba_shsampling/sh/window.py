"""Per-band windows against SH ringing (negative side lobes) and their cost.

A window is a per-band factor w_0 .. w_{n-1} (numpy float64, w_0 = 1 so the
integral is untouched). Multiplying band l of any SH function by w_l is, by
Funk-Hecke, a spherical convolution with the zonal kernel
K_w(t) = sum_l (2l+1)/(4 pi) w_l P_l(t): rotation invariant, so a window chosen
on a zonal lobe applies unchanged to that lobe turned to any axis.

Windows provided:

- ``hann_window``: h_l = (1 + cos(pi l / n)) / 2.
- ``lanczos_window``: sigma_l = sinc(l / n) = sin(pi l / n) / (pi l / n).
- ``poussin_window``: the kernel ((1 + t)/2)^(n-1) (spherical de la Vallee
  Poussin kernel). The kernel is >= 0 and has degree n-1, so it needs no
  truncation: any non-negative function stays non-negative after windowing
  to n bands, whatever its shape. Strong (w_l ~ exp(-l^2 / n)).
- ``nonnegative_window``: automatic. The tempered Poussin window
  w(t) = poussin^t with the mildest t in [0, 1] (bisection) for which a given
  zonal lobe is >= -tolerance * peak on a dense grid; t = 1 is safe by
  construction. This is the automatic negativity removal the 2009 paper left
  as future work (docs/MATH.md, section 9). (A linear blend (1-t) + t * poussin
  was tried first: it needs t > 0.95 for every Phong lobe measured, because
  the ringing sits where the exact lobe is 0.)

``window_quality`` measures a window on a zonal lobe: the minimum relative to
the peak (negativity) and the relative L2 distance to the exact lobe
(fidelity loss, truncation included).
"""

from __future__ import annotations

import math

import numpy as np

from .basis import bands_of
from .zonal import _check_band_count, zonal_profile

DEFAULT_GRID = 8192
"""Angles (uniform in theta, poles included) on which profiles are checked:
~800 points per ringing period pi/n at 32 bands."""


def hann_window(n_bands: int) -> np.ndarray:
    """Hann window h_l = (1 + cos(pi l / n)) / 2, l = 0..n-1."""
    n = _check_band_count(n_bands)
    return 0.5 * (1.0 + np.cos(np.pi * np.arange(n) / n))


def lanczos_window(n_bands: int) -> np.ndarray:
    """Lanczos sigma factors sinc(l / n) = sin(pi l / n) / (pi l / n), l = 0..n-1."""
    n = _check_band_count(n_bands)
    return np.sinc(np.arange(n) / n)


def poussin_window(n_bands: int) -> np.ndarray:
    """Legendre factors of the non-negative kernel ((1 + t)/2)^k, k = n - 1, normalised to w_0 = 1.

    w_l = (k+1) (k!)^2 / ((k-l)! (k+l+1)!), from the recurrence
    w_{l+1} = w_l (k - l) / (k + l + 2).
    """
    n = _check_band_count(n_bands)
    k = n - 1
    w = np.ones(n)
    for l in range(n - 1):
        w[l + 1] = w[l] * (k - l) / (k + l + 2)
    return w


def tempered_poussin_window(n_bands: int, strength: float) -> np.ndarray:
    """``poussin_window(n) ** strength``: identity at 0, the Poussin window at 1.

    Powers keep w_0 = 1 and monotonicity, and behave like a Gaussian roll-off
    exp(-strength l^2 / n) whose width is set by ``strength``.
    """
    if not 0.0 <= strength <= 1.0:
        raise ValueError(f"the window strength must be in [0, 1], got {strength}")
    return poussin_window(n_bands) ** strength


def profile_grid(n_grid: int = DEFAULT_GRID) -> np.ndarray:
    """cos(theta) at ``n_grid`` angles uniform in theta in [0, pi] (both poles included)."""
    return np.cos(np.linspace(0.0, np.pi, n_grid))


def _attenuation_array(attenuation) -> np.ndarray:
    lam = np.asarray(attenuation, dtype=np.float64)
    if lam.ndim != 1 or lam.size == 0:
        raise ValueError("an attenuation is a non-empty 1D list of per-band factors")
    if not np.all(np.isfinite(lam)):
        raise ValueError("the attenuation has non-finite entries")
    return lam


def nonnegative_window_strength(attenuation, tolerance: float = 0.0,
                                n_grid: int = DEFAULT_GRID, iterations: int = 40) -> float:
    """Mildest tempering t with the windowed zonal lobe >= -tolerance * its peak on the grid.

    Bisection on t in [0, 1] for ``tempered_poussin_window(n, t)``; t = 1 is
    non-negative for every non-negative lobe (float64 round-off aside, which
    the 1e-12 floor absorbs), so the returned t is always admissible on the
    grid. Negativity decreases steeply but not provably monotonically with t,
    so t is the boundary found by bisection, not a global minimiser.

    Parameter ``attenuation``:
        lambda_0 .. lambda_{n-1} of the truncated lobe (Python/numpy floats),
        a non-negative lobe before truncation (Phong, clamped cosine).

    Parameter ``tolerance`` (float):
        Accepted negativity relative to the peak of the windowed lobe. With
        0, exact non-negativity forces a strong window (the lobe's zero
        region must become a non-negative tail); 1e-4 to 1e-3 is far milder
        and harmless to a sampler that clamps at 0.

    Returns t in [0, 1]; 0 means the truncated lobe already meets the tolerance.
    """
    lam = _attenuation_array(attenuation)
    if not tolerance >= 0:
        raise ValueError(f"the tolerance must be >= 0, got {tolerance}")
    z = profile_grid(n_grid)

    def admissible(t: float) -> bool:
        f = zonal_profile(lam * tempered_poussin_window(lam.size, t), z)
        return f.min() >= -(tolerance + 1e-12) * f.max()

    if admissible(0.0):
        return 0.0
    lo, hi = 0.0, 1.0
    for _ in range(iterations):
        mid = 0.5 * (lo + hi)
        lo, hi = (lo, mid) if admissible(mid) else (mid, hi)
    return hi


def nonnegative_window(attenuation, tolerance: float = 0.0,
                       n_grid: int = DEFAULT_GRID) -> np.ndarray:
    """The automatic window: ``tempered_poussin_window(n, nonnegative_window_strength(...))``."""
    n = _attenuation_array(attenuation).size
    return tempered_poussin_window(n, nonnegative_window_strength(attenuation, tolerance, n_grid))


def apply_window(coeffs, window):
    """Multiply band l of an SH coefficient vector by ``window[l]``.

    ``coeffs``: n^2 entries (list of Dr.Jit Floats / floats, or numpy array
    with the coefficient index first); ``window``: exactly n factors.
    Returns the same kind of container.
    """
    n = bands_of(coeffs)
    w = np.asarray(window, dtype=np.float64)
    if w.shape != (n,):
        raise ValueError(f"a window for {n} bands has {n} factors, got shape {w.shape}")
    if isinstance(coeffs, np.ndarray):
        per_coeff = np.repeat(w, 2 * np.arange(n) + 1)
        return coeffs * per_coeff.reshape((-1,) + (1,) * (coeffs.ndim - 1))
    # Python floats: numpy scalars would swallow Dr.Jit operands.
    return [float(w[math.isqrt(i)]) * c for i, c in enumerate(coeffs)]


def window_quality(attenuation_exact, window, n_grid: int = DEFAULT_GRID) -> dict:
    """Negativity and fidelity of a windowed, truncated zonal lobe.

    Parameter ``attenuation_exact``:
        lambda_l of the exact lobe over enough bands L >= n for its tail to be
        negligible (e.g. ``phong_attenuation(s, 400)``).

    Parameter ``window``:
        n factors; the approximation is lambda_l w_l for l < n.

    Returns a dict with ``min_rel`` (minimum of the approximation over the
    grid divided by its maximum; negative = ringing) and ``l2_loss``
    (||approx - exact||_2 / ||exact||_2 over the sphere, by Parseval:
    ||f||^2 = sum_l (2l+1)/(4 pi) lambda_l^2).
    """
    lam = _attenuation_array(attenuation_exact)
    w = np.asarray(window, dtype=np.float64)
    n = w.size
    if n > lam.size:
        raise ValueError(f"the exact attenuation must cover the window's {n} bands")
    approx = lam[:n] * w
    values = zonal_profile(approx, profile_grid(n_grid))
    band_weight = (2 * np.arange(lam.size) + 1) / (4 * math.pi)
    diff = lam.copy()
    diff[:n] -= approx
    return {
        "min_rel": float(values.min() / values.max()),
        "l2_loss": float(math.sqrt(np.sum(band_weight * diff ** 2) / np.sum(band_weight * lam ** 2))),
    }
