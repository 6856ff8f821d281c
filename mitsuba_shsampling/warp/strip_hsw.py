"""Hierarchical sample warping of SH functions in z-first ("strip") order.

:class:`SHStripWarp` reaches the same 2^depth x 2^depth leaves of the
equal-area (z, phi) cylinder as the quadtree of :class:`.hsw.SHWarp`, but
splits in a different order:

1. ``depth`` binary splits in z of full-azimuth strips [z0, z1] x [0, 2 pi).
   Over the full circle every m != 0 term integrates to 0, so a strip's
   integral needs only the zonal coefficients f_l^0 and the m = 0
   antiderivatives: O(n) work per level (quadtree: O(n^2)).
2. One z-contraction A[m] for the chosen strip (two antiderivative rows and
   n^2 multiply-adds), then ``depth`` binary splits in phi of that strip:
   each half's integral is sum_m A[m] Phi_m, O(n) per level with the phi
   centre's cos/sin carried by angle addition.

Both phases are hierarchical warps, so the density is again the product of
the branch probabilities (clamped at 0) times the leaf density over the leaf's
solid angle: exact for the warp and safe for MIS. For a non-negative f the
leaf probabilities equal the quadtree's (leaf integral / total); where f
rings negative, the strip phase clamps only whole strips, the phi phase
clamps within the strip. The n^2 cost is paid once instead of per level, so
deep trees are cheap.

Frame and units as in :mod:`.hsw` (SH frame, z-up, per steradian).
"""

from __future__ import annotations

import math

import drjit as dr
import mitsuba as mi

from ..sh.basis import bands_of, sh_index
from ..sh.integrals import (contract_phi, contract_z, legendre_antiderivatives,
                            phi_integrals_centred, z_integrals, zonal_antiderivatives)
from .hierarchy import (TWO_PI, Cell, check_depth, grid_coordinates, grid_direction,
                        walk_pdf_1d, walk_sample_1d)
from .hsw import _as_floats, check_leaf, leaf_density, sample_leaf

DEFAULT_DEPTH = 12
"""Measured (scripts/bench_sh_warp.py, Phong s=20 at 20 bands): mean relative pdf
error 0.58 % at depth 10, 0.19 % at depth 12 for ~15 % more time; the
bilinear leaf gained little (0.52 % at depth 10) and cost ~40 % more time."""


class ZonalStripWeights:
    """1D weight provider over z: integrals of f over full-azimuth strips.

    State: the zonal antiderivative row at the strip's lower bound and the
    strip's signed integral (the upper half is the strip minus the lower half).
    """

    def __init__(self, coeffs: list):
        self.order = bands_of(coeffs) - 1
        self.zonal = [coeffs[sh_index(l, 0)] for l in range(self.order + 1)]

    def _strip_integral(self, f_lo: list, f_hi: list):
        acc = self.zonal[0] * (f_hi[0] - f_lo[0])
        for c, a, b in zip(self.zonal[1:], f_lo[1:], f_hi[1:]):
            acc = dr.fma(c, b - a, acc)
        return TWO_PI * acc

    def root(self):
        lo, hi = zonal_antiderivatives(-1.0, self.order), zonal_antiderivatives(1.0, self.order)
        return {"f_lo": [mi.Float(v) for v in lo], "total": self._strip_integral(lo, hi)}

    def children(self, state, level, z0, zm, z1):
        state["f_mid"] = zonal_antiderivatives(zm, self.order)
        state["lower"] = self._strip_integral(state["f_lo"], state["f_mid"])
        state["upper"] = state["total"] - state["lower"]
        return state["lower"], state["upper"]

    def advance(self, state, level, upper):
        return {"f_lo": [dr.select(upper, m, l) for l, m in zip(state["f_lo"], state["f_mid"])],
                "total": dr.select(upper, state["upper"], state["lower"])}


class AzimuthWeights:
    """1D weight provider over phi inside one z strip, from its row A[m]."""

    def __init__(self, coeffs: list, z0, z1):
        self.order = bands_of(coeffs) - 1
        rows = z_integrals(legendre_antiderivatives(z0, self.order),
                           legendre_antiderivatives(z1, self.order))
        self.row = contract_z(coeffs, rows, self.order)

    def root(self):
        # Centre of [0, 2 pi) is pi; its full-circle integral keeps only m = 0.
        return {"cos_c": mi.Float(-1.0), "sin_c": mi.Float(0.0), "total": TWO_PI * self.row[self.order]}

    def children(self, state, level, phi0, phim, phi1):
        h = math.pi / 2 ** (level + 1)
        cos_c, sin_c = state["cos_c"], state["sin_c"]
        cos_l = dr.fma(cos_c, math.cos(h), sin_c * math.sin(h))
        sin_l = dr.fma(sin_c, math.cos(h), -cos_c * math.sin(h))
        state["left"] = contract_phi(self.row, phi_integrals_centred(cos_l, sin_l, h, self.order))
        state["right"] = state["total"] - state["left"]
        state["centres"] = (cos_l, sin_l, h)
        return state["left"], state["right"]

    def advance(self, state, level, upper):
        cos_l, sin_l, h = state["centres"]
        # Right centre = left centre + 2h.
        cos_2h, sin_2h = math.cos(2 * h), math.sin(2 * h)
        cos_r = dr.fma(cos_l, cos_2h, -sin_l * sin_2h)
        sin_r = dr.fma(sin_l, cos_2h, cos_l * sin_2h)
        return {"cos_c": dr.select(upper, cos_r, cos_l), "sin_c": dr.select(upper, sin_r, sin_l),
                "total": dr.select(upper, state["right"], state["left"])}


class SHStripWarp:
    """Hierarchical sample warping of max(f, 0), z strips first, then phi.

    Parameter ``depth`` (int, default 12):
        Binary levels per dimension; the leaves are the same 2^depth x
        2^depth equal-area cells as :class:`.hsw.SHWarp` at that depth.
        float32 samples support depth <= 12 (one bit per level is spent).

    Parameter ``leaf`` (str, default ``"uniform"``):
        ``"uniform"`` or ``"bilinear"`` placement inside the leaf
        (see :mod:`.hsw`).

    Same interface and conventions as :class:`.hsw.SHWarp`.
    """

    def __init__(self, depth: int = DEFAULT_DEPTH, leaf: str = "uniform"):
        self.depth = check_depth(depth)
        self.leaf = check_leaf(leaf)

    def _strip(self, iz):
        """z bounds of strip ``iz`` (those of any leaf in that row)."""
        leaf = Cell(self.depth, iz, 0)
        return leaf.z0, leaf.z1

    def sample(self, coeffs, u: mi.Point2f):
        """Warp ``u`` in [0,1)^2 to a direction; returns (direction, pdf)."""
        coeffs = _as_floats(coeffs)
        iz, t_z, p_z, valid_z, _ = walk_sample_1d(ZonalStripWeights(coeffs), self.depth, u.x, -1.0, 1.0)
        iphi, t_phi, p_phi, valid_phi, _ = walk_sample_1d(
            AzimuthWeights(coeffs, *self._strip(iz)), self.depth, u.y, 0.0, TWO_PI)
        leaf = Cell(self.depth, iz, iphi)
        z, phi, density = sample_leaf(self.leaf, coeffs, leaf, mi.Point2f(t_z, t_phi))
        valid = valid_z & valid_phi
        d = dr.select(valid, grid_direction(z, phi), mi.warp.square_to_uniform_sphere(u))
        return d, dr.select(valid, p_z * p_phi * density / leaf.area, 0.0)

    def pdf(self, coeffs, d: mi.Vector3f) -> mi.Float:
        """Density (per steradian) with which :meth:`sample` produces ``d``."""
        coeffs = _as_floats(coeffs)
        z, phi = grid_coordinates(d)
        iz, p_z, _ = walk_pdf_1d(ZonalStripWeights(coeffs), self.depth, z, -1.0, 1.0)
        iphi, p_phi, _ = walk_pdf_1d(AzimuthWeights(coeffs, *self._strip(iz)), self.depth, phi, 0.0, TWO_PI)
        leaf = Cell(self.depth, iz, iphi)
        return p_z * p_phi * leaf_density(self.leaf, coeffs, leaf, z, phi) / leaf.area
