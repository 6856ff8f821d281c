"""Real spherical-harmonic basis, overflow-free to high order.

Conventions (identical to ``drjit.sh_eval``): real SH with the Condon-Shortley
phase, z-up frame, phi = atan2(y, x), flat index ``l*(l+1) + m``. ``order`` is
the highest band index l_max, so ``order + 1`` bands and ``(order+1)^2``
functions are returned.

Why a reimplementation: ``drjit.sh_eval`` stops at l_max = 9. Forming the
normalisation K_l^m and P_l^m separately overflows float32 near l = 29, so this
module runs the recurrences on the *normalised* functions and keeps the sin^m
factor inside ``Re/Im (x + i y)^m`` (no atan2, exact at the poles).
"""

from __future__ import annotations

import math

import drjit as dr
import mitsuba as mi

MAX_ORDER = 31
"""Highest band index supported (32 bands, 1024 coefficients)."""


def sh_index(l: int, m: int) -> int:
    """Flat index of y_l^m."""
    return l * (l + 1) + m


def coefficient_count(order: int) -> int:
    """Number of basis functions for highest band index ``order``."""
    return (order + 1) ** 2


def bands_of(coeffs) -> int:
    """Number of bands of a coefficient vector; raises if its length is not a square."""
    n = math.isqrt(len(coeffs))
    if n * n != len(coeffs) or n == 0:
        raise ValueError(
            f"an SH coefficient vector has n^2 entries for n bands; got {len(coeffs)}")
    return n


def as_coefficients(coeffs) -> list:
    """``coeffs`` (n^2 per-lane ``mi.Float`` or Python floats) as a list of
    ``mi.Float``; raises ValueError unless its length is a square."""
    bands_of(coeffs)
    return [c if isinstance(c, mi.Float) else mi.Float(c) for c in coeffs]


def check_order(order) -> int:
    """Validate an ``order`` (l_max) argument and return it as int."""
    if isinstance(order, bool) or not isinstance(order, int):
        raise TypeError(f"SH order must be an int (the highest band index), got {order!r}")
    if not 0 <= order <= MAX_ORDER:
        raise ValueError(f"SH order must be in [0, {MAX_ORDER}], got {order}")
    return order


# -- Recurrence constants (float64, folded into the trace as literals) ------

def _diag_factor(m: int) -> float:
    """Qb_m^m = _diag_factor(m) * Qb_{m-1}^{m-1} (CS phase included)."""
    return -math.sqrt((2 * m + 1) / (2 * m))


def _a(l: int, m: int) -> float:
    return math.sqrt((4 * l * l - 1) / (l * l - m * m))


def _b(l: int, m: int) -> float:
    return math.sqrt(((l - 1) ** 2 - m * m) / (4 * (l - 1) ** 2 - 1))


def reduced_legendre(z, order: int) -> dict:
    """Normalised associated Legendre functions divided by sin^m(theta).

    Returns ``{(l, m): Qb_l^m(z)}`` for 0 <= m <= l <= order, where
    ``K_l^m P_l^m(z) = Qb_l^m(z) * sin(theta)^m``. Each Qb is a polynomial in
    z, so it is finite and smooth at the poles. Works for any Dr.Jit float
    type (or a Python float).
    """
    q = {}
    diag = 0.5 / math.sqrt(math.pi)
    for m in range(order + 1):
        if m > 0:
            diag *= _diag_factor(m)
        q[m, m] = diag + 0 * z  # broadcast the constant to z's type
        if m + 1 <= order:
            q[m + 1, m] = math.sqrt(2 * m + 3) * z * diag
        for l in range(m + 2, order + 1):
            q[l, m] = _a(l, m) * dr.fma(z, q[l - 1, m], -_b(l, m) * q[l - 2, m])
    return q


def azimuthal_powers(x, y, order: int):
    """Re and Im of (x + i y)^m for m = 0..order (= sin^m(theta) cos/sin(m phi))."""
    c, s = [1.0 + 0 * x], [0 * x]
    for m in range(1, order + 1):
        c.append(dr.fma(x, c[-1], -y * s[-1]))
        s.append(dr.fma(x, s[-1], y * c[-2]))
    return c, s


def unit_or_zero(d):
    """(x, y, z, valid) of ``d`` normalised, for the basis evaluations.

    Invalid lanes (a zero or non-finite ``d``) become the zero vector: every
    m != 0 term then vanishes through (x + i y)^m, and the callers mask the
    m = 0 terms with ``valid``."""
    norm2 = dr.squared_norm(d)
    valid = dr.isfinite(norm2) & (norm2 > 0)
    inv = dr.rsqrt(dr.select(valid, norm2, 1))
    x, y, z = (dr.select(valid, v * inv, 0) for v in (d.x, d.y, d.z))
    return x, y, z, valid


def sh_eval(d, order: int) -> list:
    """Evaluate the real SH basis at unit directions ``d``.

    Drop-in replacement for ``drjit.sh_eval`` that also covers
    10 <= order <= 31.

    Parameter ``d`` (Array3f of any Dr.Jit float type):
        Directions, z-up. They are normalised here; a zero or non-finite
        direction yields 0 for every basis function (never NaN).

    Parameter ``order`` (int):
        Highest band index l_max (0..31).

    Returns a list of ``(order+1)^2`` arrays, index ``l*(l+1)+m``.
    """
    check_order(order)
    x, y, z, valid = unit_or_zero(d)
    q = reduced_legendre(z, order)
    c, s = azimuthal_powers(x, y, order)
    out = [None] * coefficient_count(order)
    sqrt2 = math.sqrt(2.0)
    for l in range(order + 1):
        out[sh_index(l, 0)] = dr.select(valid, q[l, 0], 0)
        for m in range(1, l + 1):
            qs = sqrt2 * q[l, m]
            out[sh_index(l, m)] = qs * c[m]
            out[sh_index(l, -m)] = qs * s[m]
    return out


def sh_eval_sum(coeffs, d):
    """Evaluate the SH expansion sum_i coeffs[i] y_i(d) (per lane)."""
    order = bands_of(coeffs) - 1
    basis = sh_eval(d, order)
    acc = coeffs[0] * basis[0]
    for ci, yi in zip(coeffs[1:], basis[1:]):
        acc = dr.fma(ci, yi, acc)
    return acc


def legendre_contraction(coeffs, z) -> dict:
    """B[m] = sum_l f_l^m Qb_l^|m|(z) for m = -order..order, per lane.

    The SH expansion on the circle of height z is then
    f(z, phi) = B[0] + sqrt(2) sum_{m>0} sin^m(theta) (B[m] cos(m phi) + B[-m] sin(m phi)):
    n^2 multiply-adds once per z, O(n) per azimuth.
    """
    order = bands_of(coeffs) - 1
    q = reduced_legendre(z, order)
    b = {}
    for m in range(-order, order + 1):
        acc = coeffs[sh_index(abs(m), m)] * q[abs(m), abs(m)]
        for l in range(abs(m) + 1, order + 1):
            acc = dr.fma(coeffs[sh_index(l, m)], q[l, abs(m)], acc)
        b[m] = acc
    return b


def sh_eval_sum_on_circle(coeffs, z, phis: list) -> list:
    """Evaluate the SH expansion at one z and several azimuths per lane.

    Separable (:func:`legendre_contraction`): n^2 multiply-adds once, then
    O(n) per azimuth. Returns one array per entry of ``phis``.
    """
    order = bands_of(coeffs) - 1
    b = legendre_contraction(coeffs, z)
    s = dr.safe_sqrt(dr.fma(-z, z, 1.0))
    out = []
    for phi in phis:
        sin_phi, cos_phi = dr.sincos(phi)
        # (s cos phi + i s sin phi)^m gives sin^m(theta) cos/sin(m phi)
        c, sn = azimuthal_powers(s * cos_phi, s * sin_phi, order)
        acc = b[0]
        for m in range(1, order + 1):
            acc += math.sqrt(2.0) * (b[m] * c[m] + b[-m] * sn[m])
        out.append(acc)
    return out
