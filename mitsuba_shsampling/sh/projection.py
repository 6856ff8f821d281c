"""Projection of spherical functions onto the real SH basis by quadrature.

The rule is a product of Gauss-Legendre in z = cos(theta) and the uniform
(midpoint) rule in phi. With ``n_z`` >= n and ``n_phi`` >= 2n - 1 it is exact
for every function band-limited to n bands: the integrand f y_l^m then
reduces, after the phi sum (exact for trigonometric polynomials of degree
< n_phi), to a polynomial in z of degree <= 2n - 2 (exact for Gauss-Legendre
with n_z >= n nodes). Functions that are not band-limited (lobes with a kink
at the horizon, sharp lobes) need more nodes in both directions.
Conventions: real SH, CS phase, z-up, index ``l*(l+1)+m`` (``sh.basis``).
"""

from __future__ import annotations

import math
from typing import Callable

import drjit as dr
import mitsuba as mi
import numpy as np

from ..device_arrays import device_array

from .basis import sh_eval

PROJECTION_CHUNK = 1 << 14
"""Directions per basis evaluation: bounds the (n^2 x chunk) float32 table to 64 MiB at 32 bands."""


def quadrature_rule(n_z: int, n_phi: int) -> tuple:
    """Directions and solid-angle weights of the (z, phi) product rule.

    The Gauss-Legendre nodes and weights come from numpy in float64 (no
    accuracy limit at large ``n_z``, unlike a float32 rule) and are rounded
    once to float32. Lane ``i * n_phi + j`` holds z-node i and azimuth
    phi_j = 2 pi (j + 1/2) / n_phi. The weights sum to 4 pi.

    Returns ``(mi.Vector3f directions, mi.Float weights)`` with
    ``n_z * n_phi`` lanes.
    """
    for name, value in (("n_z", n_z), ("n_phi", n_phi)):
        if isinstance(value, bool) or not isinstance(value, int) or value < 1:
            raise ValueError(f"{name} must be a positive int, got {value!r}")
    z, wz = np.polynomial.legendre.leggauss(n_z)
    phi = 2 * math.pi * (np.arange(n_phi) + 0.5) / n_phi
    zz, pp = np.meshgrid(z, phi, indexing="ij")
    sin_theta = np.sqrt(np.maximum(0.0, 1.0 - zz * zz))
    d = mi.Vector3f(*(device_array(mi.Float, c) for c in (sin_theta * np.cos(pp), sin_theta * np.sin(pp), zz)))
    w = device_array(mi.Float, np.repeat(wz * (2 * math.pi / n_phi), n_phi))
    return d, w


def project(func: Callable, n_bands: int, n_z: int | None = None,
            n_phi: int | None = None) -> list:
    """SH coefficients f_i = integral f(omega) y_i(omega) d omega by quadrature.

    Parameter ``func``:
        Callable taking an ``mi.Vector3f`` of unit directions (z-up, many
        lanes) and returning the function value per lane, as an ``mi.Float``
        or a numpy array (a scalar/numpy reference can call ``d.numpy()``).
        Non-finite values raise ``ValueError``.

    Parameter ``n_bands`` (int):
        Number of bands n of the result (n <= 32).

    Parameters ``n_z``, ``n_phi`` (int):
        Quadrature size; defaults n and 2n - 1 are exact for band-limited
        input (see the module docstring).

    Returns a list of n^2 ``mi.Float`` (one lane each). The basis is evaluated
    in float32 and the weighted sums are accumulated in float64.
    """
    if isinstance(n_bands, bool) or not isinstance(n_bands, int) or n_bands < 1:
        raise ValueError(f"n_bands must be a positive int, got {n_bands!r}")
    d, w = quadrature_rule(n_z or n_bands, n_phi or 2 * n_bands - 1)
    n_points = dr.width(d)
    values = func(d)
    if dr.is_array_v(values):
        values = values.numpy()
    values = np.broadcast_to(np.asarray(values, dtype=np.float64).ravel(), (n_points,)) \
        if np.size(values) in (1, n_points) else None
    if values is None:
        raise ValueError(f"func must return one value per direction ({n_points})")
    if not np.all(np.isfinite(values)):
        raise ValueError("func returned non-finite values")

    # Evaluate the basis chunk by chunk in one kernel each and reduce in numpy
    # (float64): one Dr.Jit reduction per coefficient would re-trace the whole
    # basis recurrence into n^2 separate kernels.
    weighted = w.numpy().astype(np.float64) * values
    coeffs = np.zeros(n_bands * n_bands)
    for start in range(0, n_points, PROJECTION_CHUNK):
        idx = dr.arange(mi.UInt32, start, min(start + PROJECTION_CHUNK, n_points))
        basis = sh_eval(dr.gather(mi.Vector3f, d, idx), n_bands - 1)
        dr.eval(basis)
        rows = np.stack([y.numpy() for y in basis]).astype(np.float64)
        coeffs += rows @ weighted[start:start + PROJECTION_CHUNK]
    return [mi.Float(c) for c in coeffs]
