"""Zonal (axially symmetric) lobes in real SH, described by per-band attenuation.

A zonal lobe f about a unit axis a depends only on cos(angle to a). By the
Funk-Hecke theorem its SH coefficients are

    f_l^m = lambda_l * y_l^m(a),    lambda_l = 2 pi * integral_{-1}^{1} f(t) P_l(t) dt

(P_l the unnormalised Legendre polynomial). ``lambda_l`` is the *attenuation*
(also: the convolution factor) of the lobe; the zonal coefficients of
docs/MATH.md, section 8, are z_l = sqrt((2l+1)/(4 pi)) * lambda_l, i.e. the coefficients
of the lobe aligned with +z. Conventions: real SH, Condon-Shortley phase, z-up,
index ``l*(l+1)+m`` (see ``sh.basis``). An attenuation vector for n bands is a
list of n entries, lambda_0 .. lambda_{n-1}; entries are Python floats (shared
by all lanes) or Dr.Jit Floats (one value per lane).
"""

from __future__ import annotations

import dataclasses
import math
import numbers

import drjit as dr
import mitsuba as mi
import numpy as np

from .basis import azimuthal_powers, reduced_legendre, sh_eval, sh_index, unit_or_zero

PHONG_EXPONENT_MAX = 1e30
"""Per-lane Phong exponents are clamped to this value: float32 keeps
(s - l) / (s + l + 3) == 1 there, i.e. the lobe becomes a Dirac delta
(lambda_l = 1) instead of producing inf / inf = NaN."""


def _check_band_count(n_bands) -> int:
    if isinstance(n_bands, bool) or not isinstance(n_bands, numbers.Integral):
        raise TypeError(f"the number of bands must be an int, got {n_bands!r}")
    if n_bands < 1:
        raise ValueError(f"the number of bands must be >= 1, got {n_bands}")
    return int(n_bands)


def phong_attenuation(s, n_bands: int) -> list:
    """Attenuation lambda_0 .. lambda_{n_bands-1} of the normalised Phong lobe.

    The lobe is ``(s+1)/(2 pi) * max(cos theta, 0)^s`` (unit integral over the
    sphere), so lambda_0 = 1. From the closed form
    lambda_l = (s+1) J(s, l), J(s,l) = sqrt(pi) 2^(-s-1) Gamma(s+1) /
    [Gamma(1+(s-l)/2) Gamma((s+l+3)/2)] (docs/MATH.md, section 8), the ratio of two
    Gamma pairs two bands apart gives the exact recurrence

        lambda_0 = 1,  lambda_1 = (s+1)/(s+2),
        lambda_{l+2} = lambda_l * (s-l) / (s+l+3)

    (one multiply and one divide per band, no Gamma functions, no overflow).
    For integer s the factor (s - l) vanishes, which reproduces the poles of
    the Gamma function (lambda_l = 0 for l > s of the parity of s).

    Parameter ``s`` (float or Dr.Jit Float):
        Phong exponent, s >= 0. A Python scalar that is negative or not finite
        raises ``ValueError``. A per-lane Dr.Jit Float is never checked with a
        reduction (this runs per shading point); instead, lanes with s < 0 or
        NaN are treated as s = 0 (the normalised hemisphere lobe) and s is
        clamped to ``PHONG_EXPONENT_MAX`` (+inf becomes the Dirac lobe,
        lambda_l = 1).

    Parameter ``n_bands`` (int):
        Number of bands n (l = 0 .. n-1).

    Returns a list of ``n_bands`` Python floats (scalar ``s``) or Dr.Jit Floats.
    """
    n_bands = _check_band_count(n_bands)
    if isinstance(s, numbers.Real):
        s = float(s)
        if not math.isfinite(s) or s < 0:
            raise ValueError(f"the Phong exponent must be finite and >= 0, got {s}")
    elif dr.is_array_v(s):
        # NaN fails the comparison and is mapped to 0 as well.
        s = dr.minimum(dr.select(s >= 0, s, 0), PHONG_EXPONENT_MAX)
    else:
        raise TypeError(f"the Phong exponent must be a float or a Dr.Jit Float, got {type(s)}")

    lam = [1.0 + 0 * s, (s + 1) / (s + 2)]
    for l in range(n_bands - 2):
        lam.append(lam[l] * (s - l) / (s + l + 3))
    return lam[:n_bands]


def clamped_cosine_attenuation(n_bands: int) -> list[float]:
    """Attenuation lambda_l of the clamped cosine ``max(cos theta, 0)`` (exact, float64).

    This is pi times the Phong attenuation at s = 1: lambda_0 = pi (the
    integral of the clamped cosine), lambda_1 = 2 pi / 3, lambda_l = 0 for odd
    l >= 3, and for even l >= 2 the closed form

        lambda_l = 2 pi (-1)^(l/2 + 1) / ((l-1)(l+2)) * l! / (2^l ((l/2)!)^2).

    The zonal coefficients of docs/MATH.md (section 8) are z_l = sqrt((2l+1)/(4 pi)) lambda_l
    (z_0 = sqrt(pi)/2, z_1 = sqrt(pi/3), z_2 = sqrt(5 pi)/8, z_3 = 0, ...).
    """
    return [math.pi * lam for lam in phong_attenuation(1.0, n_bands)]


def zonal_coefficients_z(attenuation) -> list:
    """Coefficients of the zonal lobe aligned with +z: only m = 0 is non-zero.

    ``f_l^0 = sqrt((2l+1)/(4 pi)) * lambda_l`` (= y_l^0(+z) lambda_l). Entries
    keep the type of ``attenuation`` (Python floats or Dr.Jit Floats); the
    result has n^2 entries for n = len(attenuation).
    """
    n = len(attenuation)
    coeffs = [0.0] * (n * n)
    for l, lam in enumerate(attenuation):
        coeffs[sh_index(l, 0)] = math.sqrt((2 * l + 1) / (4 * math.pi)) * lam
    return coeffs


def zonal_to_sh(attenuation, axis) -> list:
    """Coefficients ``f_l^m = lambda_l y_l^m(axis)`` of a zonal lobe turned to ``axis``.

    Costs one basis evaluation (n^2 functions) and n^2 multiplies per lane.

    Parameter ``attenuation``:
        List of n per-band factors lambda_l (floats or Dr.Jit Floats), e.g.
        from ``phong_attenuation``; n <= 32.

    Parameter ``axis`` (mi.Vector3f):
        Lobe axis in the SH frame (z-up). Normalised by the basis evaluation;
        a zero or non-finite axis yields all-zero coefficients.

    Returns a list of n^2 Dr.Jit Floats.
    """
    n = _check_band_count(len(attenuation))
    basis = sh_eval(axis, n - 1)
    coeffs = []
    for l in range(n):
        coeffs.extend(attenuation[l] * y for y in basis[l * l:(l + 1) ** 2])
    return coeffs


def triangle_index(l: int, m: int) -> int:
    """Index of (l, m), 0 <= m <= l, in a row-major triangle of per-(l, |m|) values."""
    return l * (l + 1) // 2 + m


@dataclasses.dataclass
class RotatedZonalLobes:
    """A sum of zonal lobes, each turned to its own per-lane axis, in factored form.

    Lobe k (attenuation lambda_l, l < n_k, unit axis a) has the coefficients
    f_l^m = lambda_l y_l^m(a) (:func:`zonal_to_sh`), which factor as

        f_l^m = g_l^|m| t_m,   g_l^m = lambda_l Qb_l^m(a_z),
        t_0 = 1,  t_m = sqrt(2) Re (a_x + i a_y)^m,  t_-m = sqrt(2) Im (a_x + i a_y)^m

    (Qb the reduced Legendre functions of :func:`~.basis.reduced_legendre`). So a
    contraction over l at fixed m, which the SH cell integrals need once per
    level (:meth:`contract_z`), costs n(n+1)/2 multiply-adds and 2n - 1 products
    per lobe instead of n^2 multiply-adds over the expanded coefficients, and
    building the lobe costs no n^2 products. :meth:`coefficients` expands it.

    Built by :func:`rotate_zonal_lobes`. Fields, one entry per lobe (Dr.Jit
    Floats in a dataclass: a value that symbolic branches and loops can carry):
    """

    legendre: tuple
    """g_l^m, 0 <= m <= l < n_k, at :func:`triangle_index` (l, m)."""
    azimuth_cos: tuple
    """t_m, m = 1 .. n_k - 1."""
    azimuth_sin: tuple
    """t_-m, m = 1 .. n_k - 1."""

    @classmethod
    def zeros(cls, band_counts) -> "RotatedZonalLobes":
        """Lobes of ``band_counts`` bands that are 0 everywhere (all fields 0)."""
        def zero(count):
            return [mi.Float(0.0) for _ in range(count)]
        return cls(tuple(zero(triangle_index(n, 0)) for n in band_counts),
                   tuple(zero(n - 1) for n in band_counts), tuple(zero(n - 1) for n in band_counts))

    @property
    def n_bands(self) -> int:
        """Bands of the sum: those of its widest lobe."""
        return max(len(c) for c in self.azimuth_cos) + 1

    def coefficients(self, n_bands: int | None = None) -> list:
        """The sum's SH coefficients f_l^m (index l(l+1)+m), for its first ``n_bands``
        bands (all by default)."""
        n = self.n_bands if n_bands is None else min(n_bands, self.n_bands)
        out = [0.0] * (n * n)
        for g, cos, sin in zip(self.legendre, self.azimuth_cos, self.azimuth_sin):
            for l in range(min(n, len(cos) + 1)):
                out[sh_index(l, 0)] = out[sh_index(l, 0)] + g[triangle_index(l, 0)]
                for m in range(1, l + 1):
                    out[sh_index(l, m)] = out[sh_index(l, m)] + g[triangle_index(l, m)] * cos[m - 1]
                    out[sh_index(l, -m)] = out[sh_index(l, -m)] + g[triangle_index(l, m)] * sin[m - 1]
        return [c + 0 * self.legendre[0][0] for c in out]  # Floats, also where no lobe reaches

    def contract_z(self, zint: dict, order: int) -> list:
        """A[m] = sum_l f_l^m zint[l, |m|] for m = -order..order (index m + order), as
        :func:`~.integrals.contract_z` of :meth:`coefficients`, in factored form: per lobe
        B[m] = sum_l g_l^m zint[l, m] once for both signs of m, then A[+-m] += t_+-m B[m]."""
        out = [None] * (2 * order + 1)

        def add(i, factor, value):
            """out[i] += factor x value (factor None: 1), one multiply-add where out[i] exists."""
            if out[i] is None:
                out[i] = value if factor is None else factor * value
            else:
                out[i] = out[i] + value if factor is None else dr.fma(factor, value, out[i])

        for g, cos, sin in zip(self.legendre, self.azimuth_cos, self.azimuth_sin):
            top = min(order, len(cos))
            for m in range(top + 1):
                acc = g[triangle_index(m, m)] * zint[m, m]
                for l in range(m + 1, top + 1):
                    acc = dr.fma(g[triangle_index(l, m)], zint[l, m], acc)
                if m == 0:
                    add(order, None, acc)
                else:
                    add(order + m, cos[m - 1], acc)
                    add(order - m, sin[m - 1], acc)
        zero = 0 * self.legendre[0][0]
        return [zero if a is None else a for a in out]


def rotate_zonal_lobes(lobes) -> RotatedZonalLobes:
    """The sum of zonal lobes ``lobes`` = [(attenuation, axis), ...], each turned to its
    per-lane axis, in the factored form of :class:`RotatedZonalLobes`.

    ``attenuation``: n_k per-band factors (floats or Dr.Jit Floats), as for
    :func:`zonal_to_sh`; ``axis`` (mi.Vector3f): the lobe's axis in the SH frame,
    normalised here; a zero or non-finite axis gives that lobe all-zero
    coefficients, as :func:`zonal_to_sh` does. Costs the basis evaluation's
    Legendre and azimuth recurrences and n(n+1)/2 products per lobe.
    """
    legendre, cos_terms, sin_terms = [], [], []
    for attenuation, axis in lobes:
        n = _check_band_count(len(attenuation))
        x, y, z, valid = unit_or_zero(axis)  # an invalid axis: its m = 0 terms masked below
        q = reduced_legendre(z, n - 1)
        c, s = azimuthal_powers(x, y, n - 1)
        g = [None] * triangle_index(n, 0)
        for l in range(n):
            g[triangle_index(l, 0)] = dr.select(valid, attenuation[l] * q[l, 0], 0)
            for m in range(1, l + 1):
                g[triangle_index(l, m)] = attenuation[l] * q[l, m]
        legendre.append(g)
        cos_terms.append([math.sqrt(2.0) * c[m] for m in range(1, n)])
        sin_terms.append([math.sqrt(2.0) * s[m] for m in range(1, n)])
    return RotatedZonalLobes(tuple(legendre), tuple(cos_terms), tuple(sin_terms))


def legendre_table(z: np.ndarray, n_bands: int) -> np.ndarray:
    """Unnormalised Legendre polynomials P_0 .. P_{n-1} at ``z`` (float64).

    Returns an array of shape ``(n_bands,) + z.shape`` (Bonnet's recurrence).
    """
    z = np.asarray(z, dtype=np.float64)
    p = np.empty((n_bands,) + z.shape)
    p[0] = 1.0
    if n_bands > 1:
        p[1] = z
    for l in range(1, n_bands - 1):
        p[l + 1] = ((2 * l + 1) * z * p[l] - l * p[l - 1]) / (l + 1)
    return p


def zonal_profile(attenuation, cos_theta) -> np.ndarray:
    """Value of the zonal lobe as a function of the cosine to its axis (float64).

    ``f(t) = sum_l (2l+1)/(4 pi) lambda_l P_l(t)``. ``attenuation`` holds
    Python floats (any length; this is the tool for dense scalar studies of
    ringing, not a per-lane evaluator). Returns an array shaped like
    ``cos_theta``.
    """
    lam = np.asarray(attenuation, dtype=np.float64)
    l = np.arange(lam.size)
    weights = (2 * l + 1) / (4 * math.pi) * lam
    return np.tensordot(weights, legendre_table(cos_theta, lam.size), axes=1)
