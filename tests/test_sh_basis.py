"""Specification of the real SH basis (`mitsuba_shsampling.sh.basis`).

Reference: scipy's complex ``sph_harm_y`` in float64. With the
Condon-Shortley phase included in both, the real basis used here is::

    y_l^0  = Re Y_l^0,   y_l^m = sqrt(2) Re Y_l^m,   y_l^-m = sqrt(2) Im Y_l^m   (m > 0)

which is also ``drjit.sh_eval``'s basis (checked below for l_max <= 9).
"""

from __future__ import annotations

import math

import drjit as dr
import mitsuba as mi
import numpy as np
import pytest
from scipy.special import sph_harm_y

from mitsuba_shsampling.sh.basis import (
    MAX_ORDER, bands_of, check_order, sh_eval, sh_eval_sum, sh_index)

ORDER = MAX_ORDER
BASIS_SCALE = math.sqrt((2 * MAX_ORDER + 1) / (4 * math.pi))
"""Largest magnitude of any basis function up to l = 31 (|y_31^0| at the poles)."""


# -- helpers ----------------------------------------------------------------

def evaluate(values) -> np.ndarray:
    """Dr.Jit arrays -> float64 numpy array of shape (len(values), lanes).

    Constant results (e.g. ``drjit.sh_eval``'s y_0^0) have one lane and are
    broadcast to the common width.
    """
    dr.eval(*values)
    rows = [np.atleast_1d(np.array(v, dtype=np.float64)) for v in values]
    lanes = max(len(r) for r in rows)
    return np.stack([np.broadcast_to(r, (lanes,)) for r in rows])


def reference_basis(dirs: np.ndarray, order: int) -> np.ndarray:
    """Real SH of unit-normalised ``dirs`` (N, 3) in float64, shape ((order+1)^2, N)."""
    d = dirs / np.linalg.norm(dirs, axis=1, keepdims=True)
    theta = np.arccos(np.clip(d[:, 2], -1.0, 1.0))
    phi = np.arctan2(d[:, 1], d[:, 0])
    out = np.empty(((order + 1) ** 2, len(d)))
    for l in range(order + 1):
        for m in range(l + 1):
            y = sph_harm_y(l, m, theta, phi)
            if m == 0:
                out[sh_index(l, 0)] = y.real
            else:
                out[sh_index(l, m)] = math.sqrt(2.0) * y.real
                out[sh_index(l, -m)] = math.sqrt(2.0) * y.imag
    return out


def sample_directions(rng: np.random.Generator) -> np.ndarray:
    """Float32 directions (N, 3): random, exact poles, the phi seam, near-poles."""
    random = rng.normal(size=(4000, 3))
    phis = np.linspace(0.0, 2.0 * np.pi, 16)
    poles = [[0.0, 0.0, 1.0], [0.0, 0.0, -1.0]]
    # phi = 0 (y = +0), phi -> 2 pi from below (y = -0 and tiny negative y)
    seam = [[c, 0.0, z] for z in (-0.9, -0.3, 0.0, 0.5, 0.99) for c in (1.0,)]
    seam += [[1.0, -0.0, 0.2], [1.0, -1e-7, 0.2], [1.0, -1e-7, -0.7], [1.0, 1e-7, 0.7]]
    near_poles = [[s * np.cos(p), s * np.sin(p), sign]
                  for s in (1e-6, 3e-7, 1e-7, 1e-8)
                  for p in phis for sign in (1.0, -1.0)]
    # approach the poles through the float32 values of z just below 1
    eps = np.array([2.0 ** -24, 2.0 ** -23, 1e-6, 1e-5, 1e-4, 1e-3])
    ring = [[math.sqrt(e * (2 - e)) * np.cos(p), math.sqrt(e * (2 - e)) * np.sin(p), sign * (1 - e)]
            for e in eps for p in phis[::3] for sign in (1.0, -1.0)]
    dirs = np.concatenate([random, poles, seam, near_poles, ring]).astype(np.float32)
    return dirs


def vector3f(dirs: np.ndarray) -> mi.Vector3f:
    return mi.Vector3f(*(np.ascontiguousarray(dirs[:, i]) for i in range(3)))


@pytest.fixture(scope="module")
def max_order_evaluation():
    """sh_eval at l_max = 31 on the test directions, with its float64 reference."""
    dirs = sample_directions(np.random.default_rng(7))
    ours = evaluate(sh_eval(vector3f(dirs), ORDER))
    # The reference sees the same float32 inputs, so only sh_eval's own
    # rounding (normalisation + recurrences) is measured.
    ref = reference_basis(dirs.astype(np.float64), ORDER)
    return dirs, ours, ref


# -- accuracy -----------------------------------------------------------------

def z_slope_bound(l: int) -> float:
    """max over the sphere and m of |d y_l^m / dz| = |y_l^0'| at the poles = K_l^0 l(l+1)/2."""
    return math.sqrt((2 * l + 1) / (4 * math.pi)) * l * (l + 1) / 2


def test_sh_eval_matches_scipy_to_float32_accuracy_for_every_band_up_to_31(max_order_evaluation):
    """|error| <= 1e-5 * BASIS_SCALE + 2^-24 * max|dy_l/dz| for every l <= 31.

    Why the second term: z is a float32 after normalisation, so a single ulp of
    z near the poles (2^-24) is amplified by the basis slope, which for y_l^0 at
    the poles is K_l^0 l(l+1)/2 (1110 at l = 31). No float32 recurrence in z
    avoids it; it only matters near the poles at high l. Measured (4000
    random + pole, seam and near-pole directions): 3.3e-5 x BASIS_SCALE at
    l = 31, within 1e-4 of a pole (83 % of the bound); <= 1e-5 x BASIS_SCALE
    everywhere for l <= 15 (6.7e-6 at l = 15, 1.3e-5 at l = 20).
    """
    _, ours, ref = max_order_evaluation
    assert np.all(np.isfinite(ours))
    for l in range(ORDER + 1):
        rows = slice(sh_index(l, -l), sh_index(l, l) + 1)
        err = np.abs(ours[rows] - ref[rows]).max()
        bound = 1e-5 * BASIS_SCALE + 2.0 ** -24 * z_slope_bound(l)
        assert err <= bound, f"band {l}: max error {err:.3g} > bound {bound:.3g}"


def test_sh_eval_is_within_about_1e5_of_basis_scale_away_from_the_poles(max_order_evaluation):
    """Where the z-conditioning term is small (|z| <= 0.99) the error is
    ~1e-5 x BASIS_SCALE: measured 9.8e-6 at l = 31 (7.8e-6 at l = 25), mostly
    the float32 normalisation's angular error times the band's slope (~l S_l).
    Asserted with 1.5x headroom so a different FMA contraction cannot flip it."""
    dirs, ours, ref = max_order_evaluation
    d = dirs.astype(np.float64)
    z = d[:, 2] / np.linalg.norm(d, axis=1)
    away = np.abs(z) <= 0.99
    assert away.sum() > 1000
    err = np.abs(ours[:, away] - ref[:, away]).max()
    assert err <= 1.5e-5 * BASIS_SCALE


def test_sh_eval_at_the_poles_is_zonal(max_order_evaluation):
    """At z = +-1 exactly every m != 0 function is exactly 0 and y_l^0 = (+-1)^l K_l^0."""
    dirs, ours, _ = max_order_evaluation
    for sign in (1.0, -1.0):
        lane = np.flatnonzero((dirs[:, 0] == 0) & (dirs[:, 1] == 0) & (dirs[:, 2] == sign))[0]
        for l in range(ORDER + 1):
            expected = sign ** l * math.sqrt((2 * l + 1) / (4 * math.pi))
            assert ours[sh_index(l, 0), lane] == pytest.approx(expected, rel=0, abs=1e-5 * BASIS_SCALE)
            others = [ours[sh_index(l, m), lane] for m in range(-l, l + 1) if m != 0]
            assert np.all(np.array(others) == 0.0)


def test_sh_eval_is_continuous_across_the_phi_seam():
    """phi = 0 and phi -> 2 pi (y = +0, -0, -1e-7) give the same values."""
    dirs = np.array([[0.6, y, 0.8] for y in (0.0, -0.0, -1e-7, 1e-7)], dtype=np.float32)
    vals = evaluate(sh_eval(vector3f(dirs), ORDER))
    np.testing.assert_allclose(vals[:, 1:], vals[:, :1] + 0 * vals[:, 1:], atol=1e-5 * BASIS_SCALE)


@pytest.mark.parametrize("order", range(10))
def test_sh_eval_is_identical_to_drjit_sh_eval_up_to_order_9(order, rng):
    """Same length, ordering and signs as ``drjit.sh_eval`` (which stops at l_max = 9)."""
    dirs = rng.normal(size=(512, 3))
    dirs = (dirs / np.linalg.norm(dirs, axis=1, keepdims=True)).astype(np.float32)
    d = vector3f(dirs)
    ours = evaluate(sh_eval(d, order))
    theirs = evaluate(dr.sh_eval(d, order))
    assert len(ours) == len(theirs) == (order + 1) ** 2
    np.testing.assert_allclose(ours, np.broadcast_to(theirs, ours.shape), rtol=0, atol=2e-6)


# -- expansions ---------------------------------------------------------------

def test_sh_eval_sum_is_the_coefficient_weighted_sum_of_the_basis(rng):
    order = 6
    coeffs = rng.normal(size=(order + 1) ** 2)
    dirs = rng.normal(size=(256, 3)).astype(np.float32)
    d = vector3f(dirs)
    total = evaluate([sh_eval_sum([mi.Float(c) for c in coeffs], d)])[0]
    expected = coeffs @ reference_basis(dirs.astype(np.float64), order)
    np.testing.assert_allclose(total, expected, rtol=0, atol=1e-5 * np.abs(coeffs).sum())


@pytest.mark.parametrize("count, bands", [(1, 1), (4, 2), (100, 10), (1024, 32)])
def test_bands_of_returns_the_band_count_of_square_lengths(count, bands):
    assert bands_of([0.0] * count) == bands


# -- bad input ----------------------------------------------------------------

@pytest.mark.parametrize("order", [-1, MAX_ORDER + 1, 100])
def test_out_of_range_order_is_a_value_error(order):
    with pytest.raises(ValueError, match="order"):
        sh_eval(mi.Vector3f(0, 0, 1), order)


@pytest.mark.parametrize("order", [2.0, "3", None, True])
def test_non_int_order_is_a_type_error(order):
    with pytest.raises(TypeError, match="order"):
        sh_eval(mi.Vector3f(0, 0, 1), order)
    with pytest.raises(TypeError):
        check_order(order)


@pytest.mark.parametrize("count", [0, 2, 3, 5, 99])
def test_coefficient_vectors_of_non_square_length_are_a_value_error(count):
    with pytest.raises(ValueError, match="n\\^2"):
        bands_of([mi.Float(1.0)] * count)
    with pytest.raises(ValueError):
        sh_eval_sum([mi.Float(1.0)] * count, mi.Vector3f(0, 0, 1))


def test_non_unit_directions_are_normalised(rng):
    dirs = rng.normal(size=(256, 3))
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    scales = rng.uniform(1e-3, 1e3, size=(256, 1))
    unit = evaluate(sh_eval(vector3f(dirs.astype(np.float32)), ORDER))
    scaled = evaluate(sh_eval(vector3f((dirs * scales).astype(np.float32)), ORDER))
    np.testing.assert_allclose(scaled, unit, rtol=0, atol=1e-4 * BASIS_SCALE)


def test_zero_and_non_finite_directions_give_all_zero_values():
    nan, inf = float("nan"), float("inf")
    bad = np.array([[0, 0, 0], [nan, 0, 1], [0, nan, 0], [nan, nan, nan],
                    [inf, 0, 0], [0, -inf, 1], [1, 0, nan]], dtype=np.float32)
    vals = evaluate(sh_eval(vector3f(bad), ORDER))
    assert not np.any(np.isnan(vals))
    assert np.all(vals == 0.0)
