"""Rotation of real SH coefficient vectors.

Contract (both functions): if ``g = rotate(f, R)`` then for every direction d

    sum_i g_i y_i(d) = sum_i f_i y_i(R^-1 d),

i.e. the function is carried along by R (a lobe about axis a ends up about
R a). Conventions: real SH, Condon-Shortley phase, z-up, index ``l*(l+1)+m``
(``sh.basis``). Rotations never mix bands, so each band is rotated by its own
(2l+1) x (2l+1) matrix.

Coefficient vectors are lists of n^2 entries (Dr.Jit Floats per lane, or Python
floats), or numpy float64 arrays of shape ``(n^2,)`` / ``(n^2, k)`` (the scalar
reference path, only with a shared rotation).
"""

from __future__ import annotations

import functools
import math

import drjit as dr
import numpy as np

from .basis import bands_of, sh_index

ROTATION_TOLERANCE = 1e-4
"""Largest accepted deviation of R^T R from the identity (and of det R from 1):
wide enough for float32 matrices, narrow enough to reject scalings/shears."""

# Ivanic & Ruedenberg's real basis for band 1 is (y, z, x) for m = -1, 0, 1,
# without the Condon-Shortley phase; this maps m to the Cartesian axis.
_AXIS_OF_M = {-1: 1, 0: 2, 1: 0}


def rotate_z(coeffs, angle):
    """Rotate a coefficient vector about +z by ``angle`` (radians, right-handed).

    Only the (m, -m) pairs of each band mix, through the 2x2 rotation by
    m * angle: O(n^2). ``angle`` is a Python float (shared) or a Dr.Jit Float
    (per lane); cos/sin(m angle) come from one sincos and the angle-addition
    recurrence.

    Returns a list of n^2 entries, or a numpy array for numpy input.
    """
    n = bands_of(coeffs)
    as_numpy = isinstance(coeffs, np.ndarray)
    if as_numpy and dr.is_array_v(angle):
        raise TypeError("numpy coefficients need a scalar angle")
    if dr.is_array_v(angle):
        s1, c1 = dr.sincos(angle)
    else:
        angle = float(angle)
        if not math.isfinite(angle):
            raise ValueError(f"the rotation angle must be finite, got {angle}")
        s1, c1 = math.sin(angle), math.cos(angle)

    out = np.array(coeffs, dtype=np.float64) if as_numpy else list(coeffs)
    cm, sm = c1, s1
    for m in range(1, n):
        for l in range(m, n):
            # f(R^-1 d) at azimuth phi is f at phi - angle:
            # a cos(m(phi-t)) + b sin(m(phi-t)) regrouped by cos/sin(m phi).
            a, b = coeffs[sh_index(l, m)], coeffs[sh_index(l, -m)]
            out[sh_index(l, m)] = a * cm - b * sm
            out[sh_index(l, -m)] = a * sm + b * cm
        cm, sm = cm * c1 - sm * s1, sm * c1 + cm * s1
    return out


def rotation_about_z(angle: float) -> np.ndarray:
    """3x3 float64 matrix of the right-handed rotation about +z by ``angle``."""
    c, s = math.cos(angle), math.sin(angle)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def _check_rotation_numpy(r: np.ndarray) -> None:
    if r.shape != (3, 3):
        raise ValueError(f"a rotation must be a 3x3 matrix, got shape {r.shape}")
    if not np.all(np.isfinite(r)):
        raise ValueError("the rotation matrix has non-finite entries")
    err = np.max(np.abs(r.T @ r - np.eye(3)))
    det = np.linalg.det(r)
    if err > ROTATION_TOLERANCE or abs(det - 1) > ROTATION_TOLERANCE:
        raise ValueError(
            "the matrix is not a rotation (orthonormal, det +1): "
            f"max |R^T R - I| = {err:.3g}, det = {det:.6g}")


def _check_rotation_lanes(r) -> None:
    """Reject per-lane matrices if any lane is not a rotation (one reduction)."""
    worst = dr.abs(dr.det(r) - 1)
    for i in range(3):
        for j in range(3):
            rtr_ij = r[0][i] * r[0][j] + r[1][i] * r[1][j] + r[2][i] * r[2][j]
            worst = dr.maximum(worst, dr.abs(rtr_ij - (1.0 if i == j else 0.0)))
    bad = ~(worst <= ROTATION_TOLERANCE)  # NaN counts as bad
    if dr.any(bad, axis=None):
        raise ValueError(
            f"{dr.count(bad, axis=None)[0]} lane(s) of the matrix are not rotations "
            "(orthonormal, det +1)")


def _ivanic_band_matrices(r: np.ndarray, n: int) -> list[np.ndarray]:
    """Band matrices of R in Ivanic & Ruedenberg's real basis (no CS phase), float64.

    Band l is built from band 1 and band l-1 (J. Phys. Chem. 1996, with the
    1998 erratum); entry ``[m + l, m' + l]``. Costs O(sum_l (2l+1)^2) = O(n^3).
    """
    r1 = np.array([[r[_AXIS_OF_M[a], _AXIS_OF_M[b]] for b in (-1, 0, 1)]
                   for a in (-1, 0, 1)])
    bands = [np.ones((1, 1)), r1][:n]
    for l in range(2, n):
        prev = bands[l - 1]

        def p(i: int, a: int, b: int) -> float:
            # Their helper P^l_{i,a,b}; prev is indexed by [a + l-1, b + l-1].
            ri = r1[i + 1]
            if b == l:
                return ri[2] * prev[a + l - 1, 2 * l - 2] - ri[0] * prev[a + l - 1, 0]
            if b == -l:
                return ri[2] * prev[a + l - 1, 0] + ri[0] * prev[a + l - 1, 2 * l - 2]
            return ri[1] * prev[a + l - 1, b + l - 1]

        band = np.zeros((2 * l + 1, 2 * l + 1))
        for m in range(-l, l + 1):
            d0 = 1.0 if m == 0 else 0.0
            am = abs(m)
            for mp in range(-l, l + 1):
                denom = (2 * l) * (2 * l - 1) if abs(mp) == l else (l + mp) * (l - mp)
                u = math.sqrt((l + m) * (l - m) / denom)
                v = 0.5 * math.sqrt((1 + d0) * (l + am - 1) * (l + am) / denom) * (1 - 2 * d0)
                w = -0.5 * math.sqrt(max(l - am - 1, 0) * (l - am) / denom) * (1 - d0)
                value = u * p(0, m, mp) if u != 0 else 0.0
                if m == 0:
                    value += v * (p(1, 1, mp) + p(-1, -1, mp))
                elif m > 0:
                    d1 = 1.0 if m == 1 else 0.0
                    value += v * (p(1, m - 1, mp) * math.sqrt(1 + d1)
                                  - p(-1, 1 - m, mp) * (1 - d1))
                    if w != 0:
                        value += w * (p(1, m + 1, mp) + p(-1, -m - 1, mp))
                else:
                    d1 = 1.0 if m == -1 else 0.0
                    value += v * (p(1, m + 1, mp) * (1 - d1)
                                  + p(-1, -m - 1, mp) * math.sqrt(1 + d1))
                    if w != 0:
                        value += w * (p(1, m - 1, mp) - p(-1, 1 - m, mp))
                band[m + l, mp + l] = value
        bands.append(band)
    return bands


def rotation_band_matrices(rotation, n_bands: int) -> list[np.ndarray]:
    """Float64 SH rotation matrices D^l (l = 0..n_bands-1) in this project's convention.

    ``g_l = D^l @ f_l`` for the band-l block (index m + l), CS phase included.
    ``rotation`` is a 3x3 rotation (array-like); anything else raises
    ``ValueError``.
    """
    r = np.asarray(rotation, dtype=np.float64)
    _check_rotation_numpy(r)
    out = []
    for l, band in enumerate(_ivanic_band_matrices(r, n_bands)):
        # Ivanic's basis function is (-1)^m times the CS one.
        sign = (-1.0) ** np.abs(np.arange(-l, l + 1))
        out.append(band * np.outer(sign, sign))
    return out


@functools.lru_cache(maxsize=None)
def _quarter_turn_matrices(n_bands: int) -> tuple:
    """D(A) and D(A^T) for A = Rx(-pi/2), which maps +z to +y (exact integer A)."""
    a = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]])
    return (tuple(rotation_band_matrices(a, n_bands)),
            tuple(rotation_band_matrices(a.T, n_bands)))


def _apply_band_matrices(mats, coeffs) -> list:
    """``g_l = D^l f_l`` with float64 matrices folded in as literals (zeros skipped)."""
    out = []
    for l, mat in enumerate(mats):
        block = coeffs[l * l:(l + 1) ** 2]
        for row in mat.tolist():  # Python floats: numpy scalars would swallow Dr.Jit operands
            acc = None
            for w, c in zip(row, block):
                if w != 0:
                    acc = w * c if acc is None else dr.fma(w, c, acc) \
                        if dr.is_array_v(c) else acc + w * c
            out.append(0.0 if acc is None else acc)
    return out


def zyz_angles(rotation) -> tuple:
    """Per-lane Euler angles with R = Rz(alpha) Ry(beta) Rz(gamma), beta in [0, pi].

    gamma is read from Rz(-alpha) R rather than from R directly, so the
    decomposition stays exact in the gimbal configurations (beta = 0 or pi),
    where alpha is arbitrary.
    """
    r = rotation
    alpha = dr.atan2(r[1][2], r[0][2])
    sa, ca = dr.sincos(alpha)
    beta = dr.atan2(dr.fma(ca, r[0][2], sa * r[1][2]), r[2][2])
    gamma = dr.atan2(dr.fma(ca, r[1][0], -sa * r[0][0]), dr.fma(ca, r[1][1], -sa * r[0][1]))
    return alpha, beta, gamma


def rotate(coeffs, rotation, check: bool = True):
    """Rotate an SH coefficient vector by a 3x3 rotation matrix (O(n^3)).

    Parameter ``coeffs``:
        n^2 coefficients: a list of Dr.Jit Floats / Python floats, or a numpy
        array of shape ``(n^2,)`` or ``(n^2, k)``.

    Parameter ``rotation``:
        Either a shared rotation (numpy 3x3 array, nested lists or
        ``mi.ScalarMatrix3f``): its band matrices are built once in float64 by
        the Ivanic-Ruedenberg recurrence and folded into the kernel as
        literals; or a per-lane ``mi.Matrix3f``: it is split into z-y-z Euler
        angles and applied as Rz(alpha) A Rz(beta) A^T Rz(gamma) with the
        constant quarter turn A (Ry(beta) = A Rz(beta) A^T), i.e. three O(n^2)
        z-rotations and two constant, half-sparse band-matrix products. This
        keeps the per-lane kernel at ~n(4n^2-1)/3 multiply-adds instead of
        building (2l+1)^2 matrix entries per band and lane. A matrix that is
        not orthonormal with det +1 (within ``ROTATION_TOLERANCE``) raises
        ``ValueError``.

    Parameter ``check`` (bool):
        Validate per-lane matrices, which costs one horizontal reduction (a
        synchronisation). Shared matrices are always checked.

    Returns the rotated vector in the form of ``coeffs`` (list or numpy).
    """
    n = bands_of(coeffs)
    per_lane = dr.is_array_v(rotation) and dr.is_jit_v(rotation)

    if not per_lane:
        mats = rotation_band_matrices(np.array(rotation, dtype=np.float64), n)
        if isinstance(coeffs, np.ndarray):
            c = np.asarray(coeffs, dtype=np.float64)
            return np.concatenate([mats[l] @ c[l * l:(l + 1) ** 2] for l in range(n)])
        return _apply_band_matrices(mats, coeffs)

    if isinstance(coeffs, np.ndarray):
        raise TypeError("numpy coefficients need a shared (numpy) rotation matrix")
    if check:
        _check_rotation_lanes(rotation)
    alpha, beta, gamma = zyz_angles(rotation)
    quarter, quarter_inv = _quarter_turn_matrices(n)
    g = rotate_z(coeffs, gamma)
    g = _apply_band_matrices(quarter_inv, g)
    g = rotate_z(g, beta)
    g = _apply_band_matrices(quarter, g)
    return rotate_z(g, alpha)
