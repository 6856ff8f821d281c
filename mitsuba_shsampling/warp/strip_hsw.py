"""Hierarchical sample warping of SH functions in z-first ("strip") order.

:class:`SHStripWarp` reaches the same 2^depth x 2^depth leaves of the
equal-area (z, phi) cylinder as the quadtree of :class:`.hsw.SHWarp`, but
splits in a different order:

1. ``depth`` binary splits in z of full-azimuth strips [z0, z1] x [0, 2 pi).
   Over the full circle every m != 0 term integrates to 0, so a strip's
   integral is G(z1) - G(z0) for one polynomial G of the zonal coefficients
   f_l^0, built once per lane; a split evaluates G once, 2 (n + 1)
   multiply-adds (quadtree: O(n^2) per level).
2. ``depth`` binary splits in phi of the chosen strip, weighted by the
   integrals of f over arcs of the strip's *middle circle*: one row
   B[m] = sum_l f_l^m P_l^m(z_mid) (n^2 multiply-adds), then each half's
   integral is sum_m B[m] Phi_m, O(n) per level with the phi centre's cos/sin
   carried by angle addition (:func:`~mitsuba_shsampling.grid.child_phi_centres`).
   A strip is 2^(1 - depth) high (1/2048 at the default depth), so the middle
   circle's profile stands for the strip's at a fraction of the cost of its
   exact z integral (two antiderivative rows).

Both phases are hierarchical warps, so the density is again the product of
the branch probabilities (clamped at 0) times the leaf density over the leaf's
solid angle: exact for the warp and safe for MIS, whatever the weights
approximate. For a non-negative f the leaf probabilities approach the
quadtree's (leaf integral / total) as the strips narrow; where f rings
negative, the strip phase clamps only whole strips, the phi phase clamps
within the strip's middle circle. The n^2 cost is paid once instead of per
level, so deep trees are cheap.

Frame and units as in :mod:`.hsw` (SH frame, z-up, per steradian).
"""

from __future__ import annotations

import math
from typing import NamedTuple

import drjit as dr
import mitsuba as mi

from ..grid import TWO_PI, Cell, child_phi_centres, grid_coordinates, grid_direction
from ..sh.basis import as_coefficients, bands_of, legendre_contraction, sh_index
from ..sh.integrals import (contract_phi, monic_legendre_series, phi_integrals_centred, strip_antiderivative_series,
                            zonal_marginal_series)
from .hierarchy import (LEAF_KINDS, Split, check_depth, check_leaf, leaf_density, linear_leaf_density, sample_leaf,
                        sample_linear_leaf, walk_pdf_1d, walk_sample_1d)
from .hsw import sh_leaf_corners

DEFAULT_DEPTH = 12
"""Depth 12 with the uniform leaf: a few times smaller pdf error than depth 10 for
a little more time, while the bilinear leaf gained little for much more time
(docs/MEASUREMENTS.md, "SH warps")."""


class StripState(NamedTuple):
    """:class:`ZonalStripWeights` state: G (see below) at the strip's lower
    bound, and the strip's signed integral."""

    g_lo: mi.Float
    total: mi.Float


class StripSplit(NamedTuple):
    g_mid: mi.Float
    lower: mi.Float
    upper: mi.Float


class ZonalStripWeights:
    """1D weight provider over z: integrals of f over full-azimuth strips.

    A strip's integral is G(z1) - G(z0) for one polynomial G per lane
    (:func:`~mitsuba_shsampling.sh.integrals.strip_antiderivative_series`,
    built once from the zonal coefficients), so a split costs one evaluation
    of G at the midpoint. State (:class:`StripState`): G at the strip's lower
    bound and the strip's signed integral (the upper half is the strip minus
    the lower half).
    """

    def __init__(self, coeffs: list):
        order = bands_of(coeffs) - 1
        zonal = [coeffs[sh_index(l, 0)] for l in range(order + 1)]
        self.series = strip_antiderivative_series(zonal)
        # Traced only where density() is called (the "linear" leaf): unused, it is dead code.
        self.marginal = zonal_marginal_series(zonal)

    def density(self, z) -> mi.Float:
        """G'(z): the function integrated over the full circle at height ``z`` (O(n))."""
        return monic_legendre_series(self.marginal, z)

    def root(self) -> StripState:
        g_lo = monic_legendre_series(self.series, -1.0)
        return StripState(g_lo, monic_legendre_series(self.series, 1.0) - g_lo)

    def children(self, state: StripState, level, z0, zm, z1) -> Split:
        g_mid = monic_legendre_series(self.series, zm)
        lower = g_mid - state.g_lo
        upper = state.total - lower
        return Split((lower, upper), StripSplit(g_mid, lower, upper))

    def advance(self, state: StripState, pending: StripSplit, level, upper) -> StripState:
        return StripState(dr.select(upper, pending.g_mid, state.g_lo),
                          dr.select(upper, pending.upper, pending.lower))


class ArcState(NamedTuple):
    """:class:`AzimuthWeights` state: cos/sin of the arc's centre and its integral."""

    cos_c: mi.Float
    sin_c: mi.Float
    total: mi.Float


class ArcSplit(NamedTuple):
    left: mi.Float
    right: mi.Float
    centres: tuple
    """(cos_left, sin_left, cos_right, sin_right) of the children's phi centres."""


class AzimuthWeights:
    """1D weight provider over phi: integrals of f over arcs of the circle at height ``z``.

    f(z, phi) = sum_m row[m] Phi'_m(phi) (cos(m phi) for m > 0, sin(|m| phi)
    for m < 0), with the row from one :func:`~mitsuba_shsampling.sh.basis.legendre_contraction`
    (n^2 multiply-adds), so an arc's integral is ``contract_phi(row, Phi)``.
    """

    def __init__(self, coeffs: list, z):
        self.order = bands_of(coeffs) - 1
        b = legendre_contraction(coeffs, z)
        # y_l^m carries sqrt(2) sin^|m|(theta) besides Qb_l^|m| for m != 0.
        sin_theta = dr.safe_sqrt(dr.fma(-z, z, 1.0))
        self.row = [None] * (2 * self.order + 1)
        self.row[self.order] = b[0]
        scale = math.sqrt(2.0) * sin_theta
        for m in range(1, self.order + 1):
            self.row[self.order + m] = scale * b[m]
            self.row[self.order - m] = scale * b[-m]
            scale = scale * sin_theta

    def values_at_ends(self, leaf: ArcState, depth: int):
        """f on the circle at the two ends of the depth-``depth`` arc whose
        centre ``leaf`` holds (angle addition with the constant half-width,
        then the Chebyshev recurrence per end: O(n), no sine or cosine)."""
        ends = child_phi_centres(leaf.cos_c, leaf.sin_c, depth - 1)
        values = []
        for cos_e, sin_e in ((ends[0], ends[1]), (ends[2], ends[3])):
            total = self.row[self.order] + 0 * cos_e
            c_prev, c_cur, s_prev, s_cur = 1.0, cos_e, 0.0, sin_e
            for m in range(1, self.order + 1):
                total = dr.fma(self.row[self.order + m], c_cur, dr.fma(self.row[self.order - m], s_cur, total))
                c_prev, c_cur = c_cur, dr.fma(2.0 * cos_e, c_cur, -c_prev)
                s_prev, s_cur = s_cur, dr.fma(2.0 * cos_e, s_cur, -s_prev)
            values.append(total)
        return values

    def root(self) -> ArcState:
        # Centre of [0, 2 pi) is pi; its full-circle integral keeps only m = 0.
        return ArcState(mi.Float(-1.0), mi.Float(0.0), TWO_PI * self.row[self.order])

    def children(self, state: ArcState, level, phi0, phim, phi1) -> Split:
        h = math.pi / 2 ** (level + 1)
        centres = child_phi_centres(state.cos_c, state.sin_c, level)
        left = contract_phi(self.row, phi_integrals_centred(centres[0], centres[1], h, self.order))
        right = state.total - left
        return Split((left, right), ArcSplit(left, right, centres))

    def advance(self, state: ArcState, pending: ArcSplit, level, upper) -> ArcState:
        cos_l, sin_l, cos_r, sin_r = pending.centres
        return ArcState(dr.select(upper, cos_r, cos_l), dr.select(upper, sin_r, sin_l),
                        dr.select(upper, pending.right, pending.left))


STRIP_LEAF_KINDS = LEAF_KINDS + ("linear",)
"""Leaf placements of :class:`SHStripWarp`: the shared ones and its own separable linear one."""


class SHStripWarp:
    """Hierarchical sample warping of max(f, 0), z strips first, then phi.

    Parameter ``depth`` (int, default 12):
        Binary levels per dimension; the leaves are the same 2^depth x
        2^depth equal-area cells as :class:`.hsw.SHWarp` at that depth.
        float32 samples support depth <= 12 (one bit per level is spent).

    Parameter ``leaf`` (str, default ``"uniform"``):
        Placement inside the leaf: ``"uniform"``, ``"bilinear"`` (see
        :mod:`.hsw`; four SH evaluations, O(n^2) each), or ``"linear"``:
        z by the linear interpolant of the strip's density in z at its two
        ends (the zonal series, O(n) each), phi by that of f on the strip's
        middle circle at the leaf's two ends (the phi phase's row, O(n)
        each). Its error falls with the square of the leaf size where the
        uniform leaf's falls with the size, so fewer levels reach the same
        pdf error (docs/MEASUREMENTS.md, "SH warps").

    Same interface and conventions as :class:`.hsw.SHWarp`.
    """

    def __init__(self, depth: int = DEFAULT_DEPTH, leaf: str = "uniform"):
        self.depth = check_depth(depth)
        self.leaf = check_leaf(leaf, STRIP_LEAF_KINDS)

    def _strip_middle(self, iz):
        """z of the middle circle of strip ``iz`` (that of any leaf in that row)."""
        return Cell(self.depth, iz, 0).zm

    def _leaf_end_values(self, strips: ZonalStripWeights, leaf: Cell, azimuth: AzimuthWeights, arc: ArcState):
        """End values of the ``"linear"`` leaf: the density in z at z0, z1, and f on
        the middle circle at phi0, phi1."""
        return [strips.density(z) for z in (leaf.z0, leaf.z1)], azimuth.values_at_ends(arc, self.depth)

    def sample(self, coeffs, u: mi.Point2f):
        """Warp ``u`` in [0,1)^2 to a direction; returns (direction, pdf)."""
        coeffs = as_coefficients(coeffs)
        strips = ZonalStripWeights(coeffs)
        iz, t_z, p_z, valid_z, _ = walk_sample_1d(strips, self.depth, u.x, -1.0, 1.0)
        azimuth = AzimuthWeights(coeffs, self._strip_middle(iz))
        iphi, t_phi, p_phi, valid_phi, arc = walk_sample_1d(azimuth, self.depth, u.y, 0.0, TWO_PI)
        leaf = Cell(self.depth, iz, iphi)
        t = mi.Point2f(t_z, t_phi)
        if self.leaf == "linear":
            z, phi, density = sample_linear_leaf(leaf, t, *self._leaf_end_values(strips, leaf, azimuth, arc))
        else:
            z, phi, density = sample_leaf(self.leaf, leaf, t, sh_leaf_corners(coeffs))
        valid = valid_z & valid_phi
        d = dr.select(valid, grid_direction(z, phi), mi.Vector3f(0.0, 0.0, 1.0))
        return d, dr.select(valid, p_z * p_phi * density / leaf.area, 0.0)

    def pdf(self, coeffs, d: mi.Vector3f) -> mi.Float:
        """Density (per steradian) with which :meth:`sample` produces ``d``."""
        coeffs = as_coefficients(coeffs)
        z, phi = grid_coordinates(d)
        strips = ZonalStripWeights(coeffs)
        iz, p_z, _ = walk_pdf_1d(strips, self.depth, z, -1.0, 1.0)
        azimuth = AzimuthWeights(coeffs, self._strip_middle(iz))
        iphi, p_phi, arc = walk_pdf_1d(azimuth, self.depth, phi, 0.0, TWO_PI)
        leaf = Cell(self.depth, iz, iphi)
        if self.leaf == "linear":
            density = linear_leaf_density(leaf, z, phi, *self._leaf_end_values(strips, leaf, azimuth, arc))
        else:
            density = leaf_density(self.leaf, leaf, z, phi, sh_leaf_corners(coeffs))
        return p_z * p_phi * density / leaf.area
