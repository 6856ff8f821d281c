"""Specification of the analytic SH cell integrals (`mitsuba_shsampling.sh.integrals`).

Cells are those of the equal-area (z, phi) hierarchy (docs/ARCHITECTURE.md):
level k has 2^k x 2^k cells, cell (iz, iphi) covers
z in [-1 + 2 iz / 2^k, -1 + 2 (iz+1) / 2^k], phi in [2 pi iphi / 2^k, 2 pi (iphi+1) / 2^k].

Reference: adaptive float64 quadrature (``scipy.integrate.quad_vec``) of
scipy's ``sph_harm_y``. The real basis is a product f(z) g(phi), so the cell
integral is the product of a z quadrature and a phi quadrature. The reference
uses the float32-rounded cell bounds that the kernels receive: phi bounds are
not exact in float32, and at depth 12 one ulp of phi (4e-7) is 3e-4 of a
cell's width, far more than the integration error being measured.

Errors are stated relative to ``cell area x S_l`` with S_l = sqrt((2l+1)/(4 pi))
(the largest value of any function of band l), i.e. relative to the largest
integral a band-l function can have over that cell.
"""

from __future__ import annotations

import math

import drjit as dr
import mitsuba as mi
import numpy as np
import pytest
from scipy.integrate import quad_vec
from scipy.special import sph_harm_y

from mitsuba_shsampling.sh.basis import MAX_ORDER, sh_index
from mitsuba_shsampling.sh.integrals import (cell_integrals, function_cell_integral, monic_legendre_series,
                                             strip_antiderivative_series)

ORDER = MAX_ORDER
DEPTHS = (0, 1, 2, 4, 6, 8, 10, 12)
FAMILY_DEPTHS = (0, 1, 3, 6, 9, 11)  # parents whose four children are also integrated

# A subsample of (l, m): every band edge (m = +-l), the zonal, and a middle m,
# for low, middle and the highest bands.
SAMPLED_LM = sorted({(l, m) for l in (0, 1, 2, 3, 5, 8, 13, 19, 24, 30, 31)
                     for m in (-l, -(l // 2), -1, 0, 1, l // 2, l) if abs(m) <= l})


# -- cells --------------------------------------------------------------------

def cell_bounds(depth: np.ndarray, iz: np.ndarray, iphi: np.ndarray):
    """Float32 (z0, z1, phi0, phi1) of hierarchy cells (exact in z for depth <= 23)."""
    n = 2.0 ** depth
    return ((-1 + 2 * iz / n).astype(np.float32), (-1 + 2 * (iz + 1) / n).astype(np.float32),
            (2 * np.pi * iphi / n).astype(np.float32), (2 * np.pi * (iphi + 1) / n).astype(np.float32))


def probe_cells() -> np.ndarray:
    """(depth, iz, iphi) rows: at every depth, cells at both poles, the equator and
    a generic row, crossed with both sides of the phi seam and a middle column."""
    rows = set()
    for k in DEPTHS:
        n = 2 ** k
        for iz in {0, n - 1, n // 2, n // 3}:
            for iphi in {0, n - 1, n // 2}:
                rows.add((k, iz, iphi))
    return np.array(sorted(rows))


def family_cells() -> tuple[np.ndarray, np.ndarray]:
    """Parents (P, 3) at the poles, equator and seam, and their children (P, 4, 3)
    in the documented order (a, b) = (0,0), (0,1), (1,0), (1,1)."""
    parents = []
    for k in FAMILY_DEPTHS:
        n = 2 ** k
        parents += sorted({(k, iz, iphi) for iz in (0, n - 1, n // 2) for iphi in (0, n - 1)})
    parents = np.array(parents)
    children = np.array([[(k + 1, 2 * iz + a, 2 * iphi + b) for a in (0, 1) for b in (0, 1)]
                         for k, iz, iphi in parents])
    return parents, children


# -- references ---------------------------------------------------------------

def reference_cell_integrals(z0, z1, phi0, phi1, lm) -> np.ndarray:
    """Float64 quadrature of y_l^m over each cell, shape (len(lm), cells)."""
    ls = np.array([l for l, _ in lm])
    ms = np.array([m for _, m in lm])
    tilde = np.where(ms == 0, 1.0, math.sqrt(2.0))

    def z_factor(z):  # K~ P_l^|m|(z), Condon-Shortley phase as in sph_harm_y
        return tilde * sph_harm_y(ls, np.abs(ms), math.acos(min(max(z, -1.0), 1.0)), 0.0).real

    def phi_factor(phi):
        return np.where(ms == 0, 1.0, np.where(ms > 0, np.cos(ms * phi), np.sin(-ms * phi)))

    out = np.empty((len(lm), len(z0)))
    for i, bounds in enumerate(zip(z0, z1, phi0, phi1)):
        a, b, c, d = (float(v) for v in bounds)
        iz, _ = quad_vec(z_factor, a, b, epsabs=1e-15, epsrel=1e-12)
        ip, _ = quad_vec(phi_factor, c, d, epsabs=1e-15, epsrel=1e-12)
        out[:, i] = iz * ip
    return out


def band_scale(lm) -> np.ndarray:
    return np.array([math.sqrt((2 * l + 1) / (4 * math.pi)) for l, _ in lm])


def to_numpy(values) -> np.ndarray:
    dr.eval(*values)
    return np.stack([np.array(v, dtype=np.float64) for v in values])


# -- shared evaluation (one kernel per path, reused by every test) -------------
#
# An l_max = 31 kernel that outputs all 1024 integrals takes seconds to
# compile; the accuracy probes only read SAMPLED_LM, so only those outputs are
# evaluated there (Dr.Jit then compiles a small kernel).

@pytest.fixture(scope="module")
def probes():
    """Default and precise cell_integrals on the probe cells (SAMPLED_LM only),
    with the quadrature reference. Arrays have shape (len(SAMPLED_LM), cells)."""
    rows = probe_cells()
    z0, z1, phi0, phi1 = cell_bounds(*rows.T)
    args = [mi.Float(v) for v in (z0, z1, phi0, phi1)]
    idx = [sh_index(l, m) for l, m in SAMPLED_LM]
    return dict(
        depth=rows[:, 0],
        area=(z1.astype(np.float64) - z0) * (phi1.astype(np.float64) - phi0),
        default=to_numpy([cell_integrals(*args, ORDER)[i] for i in idx]),
        precise=to_numpy([cell_integrals(*args, ORDER, precise=True)[i] for i in idx]),
        reference=reference_cell_integrals(z0, z1, phi0, phi1, SAMPLED_LM),
    )


@pytest.fixture(scope="module")
def families():
    """All 1024 default cell integrals and function_cell_integral of a random
    l_max = 31 expansion on the whole sphere followed by parent cells and their
    children (parents (P,), children (P, 4))."""
    parents, children = family_cells()
    rows = np.concatenate([[(0, 0, 0)], parents, children.reshape(-1, 3)])
    z0, z1, phi0, phi1 = cell_bounds(*rows.T)
    args = [mi.Float(v) for v in (z0, z1, phi0, phi1)]
    coeffs = np.random.default_rng(3).normal(size=(ORDER + 1) ** 2)
    p = len(parents)
    function = to_numpy([function_cell_integral([mi.Float(c) for c in coeffs], *args)])[0]
    return dict(
        coeffs=coeffs,
        area=(z1.astype(np.float64) - z0) * (phi1.astype(np.float64) - phi0),
        basis=to_numpy(cell_integrals(*args, ORDER)),
        function=function,
        parents=function[1:1 + p],
        children=function[1 + p:].reshape(p, 4),
        parent_area=((z1.astype(np.float64) - z0) * (phi1.astype(np.float64) - phi0))[1:1 + p],
    )


def relative_errors(probes, path: str, depth: int) -> np.ndarray:
    """|error| / (cell area x S_l) at one depth, shape (len(SAMPLED_LM), cells)."""
    at = probes["depth"] == depth
    err = np.abs(probes[path][:, at] - probes["reference"][:, at])
    return err / (probes["area"][None, at] * band_scale(SAMPLED_LM)[:, None])


def expansion_scale(coeffs: np.ndarray) -> float:
    """sum_i |c_i| S_l(i): bounds |f| on the sphere, so area x this bounds a cell integral."""
    return float(np.sum(np.abs(coeffs) * band_scale(
        [(l, m) for l in range(ORDER + 1) for m in range(-l, l + 1)])))


# -- accuracy against quadrature ----------------------------------------------

def default_path_bound(depth: int) -> float:
    """Error bound of the float32 path, relative to cell area x S_l.

    z factor: a difference of two float32 antiderivative values, each of
    magnitude below S_l, so its absolute error is a few 2^-24 S_l whatever the
    cell: relative to dz S_l that is 2 * 2^-24 / dz (dz = 2^(1-depth)).
    phi factor: cos/sin(m c) of the float32 midpoint c are off by up to
    |m| ulp(pi)/2 = 3.7e-6 at m = 31; 1e-5 covers it at any depth.
    Measured (l_max 31, SAMPLED_LM, probe cells): 6.6e-5 at depth 12,
    2.6e-5 at depth 10, 7.3e-6 at depth 8, <= 4.1e-6 above (bounds: 2.5e-4,
    7.1e-5, 2.5e-5, <= 1.4e-5).
    """
    dz = 2.0 ** (1 - depth)
    return 2.0 * 2.0 ** -24 / dz + 1e-5


PRECISE_PATH_BOUND = 2.5e-7
"""The precise path rounds float64 factors once each, then multiplies in float32:
a few float32 ulps (2^-24 = 6e-8). Measured: <= 8.5e-8 at every depth 0..12."""


@pytest.mark.parametrize("depth", DEPTHS)
def test_default_cell_integrals_match_quadrature_within_the_float32_cancellation_bound(probes, depth):
    worst = relative_errors(probes, "default", depth).max()
    assert worst <= default_path_bound(depth), f"depth {depth}: {worst:.3g}"


@pytest.mark.parametrize("depth", DEPTHS)
def test_precise_cell_integrals_match_quadrature_to_float32_rounding_at_every_depth(probes, depth):
    worst = relative_errors(probes, "precise", depth).max()
    assert worst <= PRECISE_PATH_BOUND, f"depth {depth}: {worst:.3g}"


def test_precise_path_is_more_accurate_than_the_default_path_for_small_cells(probes):
    """The reason precise=True exists: at depth 12 the default path's cancellation dominates."""
    default = relative_errors(probes, "default", 12).max()
    precise = relative_errors(probes, "precise", 12).max()
    assert precise * 10 < default


def test_sphere_integral_of_y00_is_sqrt_4pi_and_of_every_other_function_zero(families):
    """All 1024 functions up to l = 31, default (float32) path. Measured: y_0^0
    off by 9.7e-8 relative, the others at most 1.3e-7 (a couple of ulps of 1)."""
    whole_sphere = families["basis"][:, 0]
    assert whole_sphere[0] == pytest.approx(math.sqrt(4 * math.pi), rel=5e-7)
    assert np.abs(whole_sphere[1:]).max() <= 1e-6


# -- consistency --------------------------------------------------------------

def test_four_children_sum_to_their_parent(families):
    """Random l_max = 31 expansion; parents at depths 0..11 at both poles, the
    equator and both sides of the phi seam."""
    scale = families["parent_area"] * expansion_scale(families["coeffs"])
    mismatch = np.abs(families["children"].sum(axis=1) - families["parents"])
    # Measured <= 6.4e-8 x scale: the float32 cancellation (default_path_bound)
    # concerns single basis functions; summed over 1024 random coefficients
    # the errors average out against expansion_scale.
    np.testing.assert_array_less(mismatch, 1e-6 * scale)


def test_function_cell_integral_is_the_coefficient_weighted_sum_of_cell_integrals(families):
    expected = families["coeffs"] @ families["basis"]
    scale = families["area"] * expansion_scale(families["coeffs"])
    # Measured <= 2.5e-9 x scale (the same float32 operations, summed in another order).
    np.testing.assert_array_less(np.abs(families["function"] - expected), 1e-7 * scale)


@pytest.mark.parametrize("order", [0, 1, 4, 19, 31])
def test_strip_series_gives_the_integral_over_full_azimuth_strips(order):
    """G(z1) - G(z0) of strip_antiderivative_series is the integral of the
    expansion over [z0, z1] x [0, 2 pi): 2 pi times the zonal part's z integral
    (float64 reference: numpy's Legendre antiderivative). Strips from the
    whole sphere down to depth 12, at both poles and inside."""
    rng = np.random.default_rng(order)
    zonal = rng.normal(size=order + 1)
    norms = np.sqrt((2 * np.arange(order + 1) + 1) / (4 * math.pi))
    antiderivative = np.polynomial.legendre.legint(zonal * norms)
    series = strip_antiderivative_series([mi.Float(c) for c in zonal])
    for z0, width in [(-1.0, 2.0), (-1.0, 2.0**-11), (1.0 - 2.0**-11, 2.0**-11), (0.3, 2.0**-6), (-0.7, 0.5)]:
        z0, z1 = np.float32(z0), np.float32(z0 + width)
        reference = 2 * math.pi * (np.polynomial.legendre.legval(float(z1), antiderivative)
                                   - np.polynomial.legendre.legval(float(z0), antiderivative))
        g = monic_legendre_series(series, mi.Float([z0, z1])).numpy().astype(np.float64)
        # A difference of two float32 values of G, so the error is a few ulps
        # of |G| ~ |zonal|_1 whatever the width. Measured <= 1.1e-7 |zonal|_1.
        assert abs((g[1] - g[0]) - reference) <= 1e-6 * np.abs(zonal).sum()


# -- bad input ----------------------------------------------------------------

@pytest.mark.parametrize("order, error", [(-1, ValueError), (32, ValueError),
                                          (3.0, TypeError), (True, TypeError)])
def test_cell_integrals_reject_bad_orders(order, error):
    with pytest.raises(error, match="order"):
        cell_integrals(mi.Float(-1), mi.Float(1), mi.Float(0), mi.Float(1), order)


@pytest.mark.parametrize("count", [0, 2, 3, 8, 1025])
def test_function_cell_integral_rejects_non_square_coefficient_vectors(count):
    with pytest.raises(ValueError, match="n\\^2"):
        function_cell_integral([mi.Float(1.0)] * count,
                               mi.Float(-1), mi.Float(1), mi.Float(0), mi.Float(1))
