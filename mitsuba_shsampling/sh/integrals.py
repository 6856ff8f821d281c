"""Analytic integrals of the real SH basis over equal-area (z, phi) cells.

On the cylinder z = cos(theta), phi in [0, 2 pi) the solid angle is dz dphi,
so the integral of y_l^m over a cell [z0, z1] x [phi0, phi1] separates::

    K~_l^m * I_l^|m|(z0, z1) * Phi_m(phi0, phi1)

with I the integral of P_l^|m| in z and Phi_m the integral of cos/sin(|m| phi).
This module provides both factors and the contractions that make a 2x2 split
of a cell cost about 2 n^2 multiply-adds (the "separable sweep"):

1. ``legendre_antiderivatives(z, order)``: K~_l^m F_l^m(z), F' = P_l^m
   (normalisation folded into the recurrence so nothing overflows).
2. ``contract_z(coeffs, I)``: A[m] = sum_l f_l^m K~ I_l^|m|   (n^2 MACs)
3. ``contract_phi(A, Phi)``: sum_m A[m] Phi_m                  (2n-1 MACs)

Precision: I is a difference of two antiderivative values, so small cells
cancel. In float32 a depth-12 cell (width 2^-11 in z) loses ~1e-4 relative.
``cell_integrals(..., precise=True)`` evaluates the antiderivatives in float64
and is exact to float32 rounding at any depth. The phi factor is computed in
product form (2/m sin(m dphi/2) cos(m phi_c)), which never cancels.
"""

from __future__ import annotations

import functools
import math

import drjit as dr

from .basis import _diag_factor, check_order, reduced_legendre, sh_index


def _k_ratio_sq(l_num: int, l_den: int, m: int) -> float:
    """(K_{l_num}^m / K_{l_den}^m)^2."""
    r = (2 * l_num + 1) / (2 * l_den + 1)
    return r * math.exp(math.lgamma(l_num - m + 1) - math.lgamma(l_num + m + 1)
                        - math.lgamma(l_den - m + 1) + math.lgamma(l_den + m + 1))


def legendre_antiderivatives(z, order: int) -> dict:
    """Antiderivatives of the normalised associated Legendre functions.

    Returns ``{(l, m): K~_l^m F_l^m(z)}`` for 0 <= m <= l <= order, where
    dF_l^m/dz = P_l^m(z) (Condon-Shortley phase, sin^m(theta) included) and
    K~ = K_l^0 for m = 0, sqrt(2) K_l^m otherwise. The integration constant is
    arbitrary but consistent, so only differences are meaningful.

    Recurrences (docs/MATH.md, section 4), with s = sqrt(1 - z^2)::

        F_m^m     ~ G_m(z),  G_m = antiderivative of s^m
        F_{m+1}^m ~ -s^(m+2) / (m+2)
        F_{l+1}^m = [(l+m)(l-1) F_{l-1}^m - (2l+1)(1-z^2) P_l^m] / ((l+2)(l-m+1))
    """
    check_order(order)
    one_minus_z2 = dr.fma(-z, z, 1.0)
    s = dr.sqrt(dr.maximum(one_minus_z2, 0.0))
    q = reduced_legendre(z, order)

    # s^m and G_m (antiderivative of s^m) for m = 0..order
    s_pow = [1.0 + 0 * z]
    for m in range(1, order + 3):
        s_pow.append(s_pow[-1] * s)
    g = [z, 0.5 * (z * s + dr.asin(dr.clip(z, -1.0, 1.0)))]
    for m in range(2, order + 1):
        g.append(z * s_pow[m] / (m + 1) + (m / (m + 1)) * g[m - 2])

    f = {}
    diag = 0.5 / math.sqrt(math.pi)
    for m in range(order + 1):
        if m > 0:
            diag *= _diag_factor(m)
        tilde = 1.0 if m == 0 else math.sqrt(2.0)
        f[m, m] = (tilde * diag) * g[m]
        if m + 1 <= order:
            f[m + 1, m] = (-tilde * diag * math.sqrt(2 * m + 3) / (m + 2)) * s_pow[m + 2]
        for l in range(m + 1, order):
            # P-term uses the normalised P_l^m = Qb_l^m s^m (already K-scaled).
            c_prev = (l + m) * (l - 1) * math.sqrt(_k_ratio_sq(l + 1, l - 1, m))
            c_p = (2 * l + 1) * math.sqrt(_k_ratio_sq(l + 1, l, m))
            denom = (l + 2) * (l - m + 1)
            p_lm = tilde * q[l, m] * s_pow[m]
            f[l + 1, m] = (c_prev / denom) * f[l - 1, m] - (c_p / denom) * one_minus_z2 * p_lm
    return f


@functools.lru_cache(maxsize=None)
def constant_antiderivatives(z: float, order: int) -> dict:
    """:func:`legendre_antiderivatives` at a constant ``z``, as Python floats,
    computed once per (z, order). Integrators trace their kernels again at
    every render pass, and the hierarchy's top levels use the same few
    constant rows each time. The returned dict is shared: do not modify it."""
    return {key: float(value) for key, value in legendre_antiderivatives(float(z), order).items()}


def z_integrals(f_lo: dict, f_hi: dict) -> dict:
    """K~ I_l^m over [z_lo, z_hi] from two antiderivative tables."""
    return {key: f_hi[key] - f_lo[key] for key in f_hi}


def phi_integrals(phi0, phi1, order: int) -> list:
    """Integrals of the azimuthal factors over [phi0, phi1].

    Returns a list indexed ``m + order`` for m = -order..order::

        m = 0: phi1 - phi0
        m > 0: integral of cos(m phi) = 2/m sin(m h) cos(m c)
        m < 0: integral of sin(|m| phi) = 2/|m| sin(|m| h) sin(|m| c)

    with c = (phi0 + phi1)/2, h = (phi1 - phi0)/2 (product form: no
    cancellation for narrow intervals).
    """
    c = 0.5 * (phi0 + phi1)
    h = 0.5 * (phi1 - phi0)
    sin_h, cos_h = dr.sincos(h)
    sin_c, cos_c = dr.sincos(c)
    out = [None] * (2 * order + 1)
    out[order] = 2.0 * h
    # Chebyshev recurrences for sin(m h), cos(m c), sin(m c)
    sh_prev, sh_cur = 0.0 * h, sin_h
    cc_prev, cc_cur = 1.0 + 0.0 * c, cos_c
    sc_prev, sc_cur = 0.0 * c, sin_c
    for m in range(1, order + 1):
        w = (2.0 / m) * sh_cur
        out[order + m] = w * cc_cur
        out[order - m] = w * sc_cur
        sh_prev, sh_cur = sh_cur, 2.0 * cos_h * sh_cur - sh_prev
        cc_prev, cc_cur = cc_cur, 2.0 * cos_c * cc_cur - cc_prev
        sc_prev, sc_cur = sc_cur, 2.0 * cos_c * sc_cur - sc_prev
    return out


def contract_z(coeffs: list, zint: dict, order: int) -> list:
    """A[m] = sum_l coeffs[l, m] K~ I_l^|m| for m = -order..order (index m + order)."""
    out = [None] * (2 * order + 1)
    for m in range(-order, order + 1):
        acc = None
        for l in range(abs(m), order + 1):
            term = coeffs[sh_index(l, m)]
            acc = term * zint[l, abs(m)] if acc is None else dr.fma(term, zint[l, abs(m)], acc)
        out[m + order] = acc
    return out


def contract_phi(a: list, phi: list):
    """sum over m of A[m] * Phi_m (both indexed m + order).

    Summed from m = 0 outwards, the order in which the recurrences of
    :func:`phi_integrals` produce Phi_m, into four accumulators: the
    hierarchical walks wait for this sum at every level, and one accumulator
    run from m = -order would be a chain of 2 order + 1 dependent
    multiply-adds that could only start after the last Phi_m.
    """
    order = len(a) // 2
    outwards = [order] + [order + sign * m for m in range(1, order + 1) for sign in (1, -1)]
    sums = [a[i] * phi[i] for i in outwards[:4]]
    for j, i in enumerate(outwards[4:]):
        sums[j % 4] = dr.fma(a[i], phi[i], sums[j % 4])
    while len(sums) > 1:
        sums = [x + y for x, y in zip(sums[::2], sums[1::2])] + sums[len(sums) - len(sums) % 2:]
    return sums[0]


def cell_integrals(z0, z1, phi0, phi1, order: int, precise: bool = False) -> list:
    """Integral of every basis function y_l^m over the cell [z0,z1] x [phi0,phi1].

    Returns ``(order+1)^2`` arrays (index l(l+1)+m) of the same type as z0.
    ``precise=True`` evaluates both factors in float64 and rounds only the
    results: the z antiderivatives, whose difference cancels for tiny cells,
    and the phi factor, whose float32 midpoint (phi0 + phi1)/2 is off by up to
    ulp(pi)/2 and so costs up to |m| * 1.2e-7 relative (4e-6 at m = 31).
    """
    check_order(order)
    ztype = type(z0)
    if precise and not isinstance(z0, float):
        f64 = dr.float64_array_t(ztype)
        zi = z_integrals(legendre_antiderivatives(f64(z0), order),
                         legendre_antiderivatives(f64(z1), order))
        zi = {k: ztype(v) for k, v in zi.items()}
        ph = [ztype(v) for v in phi_integrals(f64(phi0), f64(phi1), order)]
    else:
        zi = z_integrals(legendre_antiderivatives(z0, order),
                         legendre_antiderivatives(z1, order))
        ph = phi_integrals(phi0, phi1, order)
    out = [None] * (order + 1) ** 2
    for l in range(order + 1):
        for m in range(-l, l + 1):
            out[sh_index(l, m)] = zi[l, abs(m)] * ph[m + order]
    return out


def function_cell_integral(coeffs: list, z0, z1, phi0, phi1):
    """Integral of the SH expansion ``coeffs`` over one cell per lane."""
    from .basis import bands_of
    order = bands_of(coeffs) - 1
    zi = z_integrals(legendre_antiderivatives(z0, order), legendre_antiderivatives(z1, order))
    return contract_phi(contract_z(coeffs, zi, order), phi_integrals(phi0, phi1, order))


def _monic_legendre_leading(k: int) -> float:
    """Leading coefficient of P_k: P_k = lead * Pm_k with Pm_k monic."""
    return math.comb(2 * k, k) / 2.0**k


def _monic_legendre_gamma(k: int) -> float:
    """gamma_k of the monic Legendre recurrence Pm_{k+1} = z Pm_k - gamma_k Pm_{k-1}."""
    return k * k / (4.0 * k * k - 1.0)


def strip_antiderivative_series(zonal: list) -> list:
    """Antiderivative of a function's integral over full-azimuth strips, as a series.

    ``zonal`` holds the m = 0 coefficients f_l^0, l = 0..order. Over the full
    circle every m != 0 term integrates to 0, so the integral over the strip
    [z0, z1] x [0, 2 pi) is G(z1) - G(z0) with

        G(z) = 2 pi sum_l f_l^0 K_l^0 F_l(z),   F_0 = z,
        F_l = (P_{l+1} - P_{l-1}) / (2l + 1)   (l >= 1, from (2l+1) P_l = (P_{l+1} - P_{l-1})'),

    a polynomial of degree order + 1. Returns its coefficients e_k,
    k = 0..order+1, in the *monic* Legendre basis Pm_k = P_k / lead_k
    (evaluate with :func:`monic_legendre_series`): O(n) once per lane, after
    which every G(z) costs 2 (order + 2) multiply-adds. The constant term is
    dropped (only differences of G are meaningful). The monic basis is as well
    conditioned on [-1, 1] as the Legendre one, unlike the power basis.
    """
    order = len(zonal) - 1
    terms = [2.0 * math.pi * math.sqrt((2 * l + 1) / (4.0 * math.pi)) for l in range(order + 1)]
    series = [0.0]
    for k in range(1, order + 2):
        d = None  # coefficient of P_k: from F_{k-1} (+) and F_{k+1} (-)
        if k - 1 <= order:
            d = zonal[k - 1] * (terms[k - 1] / (2 * k - 1))
        if k + 1 <= order:
            d = dr.fma(zonal[k + 1], -terms[k + 1] / (2 * k + 3), d)
        series.append(d * _monic_legendre_leading(k))
    return series


def zonal_marginal_series(zonal: list) -> list:
    """The density in z of a function integrated over full circles, as a series.

    g(z) = dG/dz = 2 pi sum_l f_l^0 K_l^0 P_l(z) (:func:`strip_antiderivative_series`
    without the antiderivative), a polynomial of degree ``order``, with
    coefficients in the monic Legendre basis for :func:`monic_legendre_series`.
    """
    series = [f * (2.0 * math.pi * math.sqrt((2 * l + 1) / (4.0 * math.pi)) * _monic_legendre_leading(l))
              for l, f in enumerate(zonal)]
    return series + [0.0] * (2 - len(series))  # monic_legendre_series wants two terms


def monic_legendre_series(series: list, z):
    """sum_k series[k] Pm_k(z) over the monic Legendre polynomials.

    The Pm_k come from their forward recurrence (stable on [-1, 1]) and the
    sum is split in two accumulators: the only dependent chain is the
    recurrence, one multiply-add per term, which the hierarchical walks wait
    for at every level (Clenshaw's backward sum has two per term).
    """
    p_prev, p = 1.0, z
    sums = [series[0], series[1] * z]
    for k in range(1, len(series) - 1):
        p_prev, p = p, dr.fma(z, p, -_monic_legendre_gamma(k) * p_prev)
        sums[(k + 1) % 2] = dr.fma(series[k + 1], p, sums[(k + 1) % 2])
    return sums[0] + sums[1]


def phi_integrals_centred(cos_c, sin_c, half_width: float, order: int) -> list:
    """:func:`phi_integrals` of [c - h, c + h] from cos(c), sin(c) and a constant h.

    In a dyadic hierarchy the half-width of every cell at a level is the
    same Python float, so the factors 2/m sin(m h) are constants folded into
    the trace and no per-lane sine or cosine is evaluated: cos/sin(m c) come
    from the Chebyshev recurrence on the carried cos(c), sin(c). Same layout
    as :func:`phi_integrals` (index ``m + order``).
    """
    out = [None] * (2 * order + 1)
    out[order] = 2.0 * half_width + 0 * cos_c
    cc_prev, cc_cur = 1.0, cos_c
    sc_prev, sc_cur = 0.0, sin_c
    two_cos = 2.0 * cos_c
    for m in range(1, order + 1):
        w = 2.0 / m * math.sin(m * half_width)
        out[order + m] = w * cc_cur
        out[order - m] = w * sc_cur
        cc_prev, cc_cur = cc_cur, dr.fma(two_cos, cc_cur, -cc_prev)
        sc_prev, sc_cur = sc_cur, dr.fma(two_cos, sc_cur, -sc_prev)
    return out
