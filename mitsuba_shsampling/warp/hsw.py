"""Hierarchical sample warping of spherical-harmonic functions (quadtree order).

:class:`SHWarp` draws directions distributed like max(f, 0) for an SH
expansion f given per lane (each SIMD lane may carry its own coefficient
vector) and evaluates the exact density of that warp for any direction.
This is the method of Jarosz et al. 2009: a 2x2 split of the equal-area
(z, phi) cylinder at every level. :mod:`.strip_hsw` splits the same leaves
in a cheaper order.

Node weights are analytic integrals of f over (z, phi) cells, computed with
the separable sweep of :mod:`mitsuba_shsampling.sh.integrals`: per level one
row of Legendre antiderivatives at the new z midpoint (the lower bound's row
is carried down the tree), one z-contraction (n^2 multiply-adds) for the lower
half (the upper half is the parent row minus it), and two phi-contractions for
the left and two for the right children. The phi half-width of a
level is a Python constant and the cell centre's cos/sin is carried down the
tree by angle addition, so no sine or cosine is evaluated per level. Negative
cell integrals (SH ringing) are clamped to probability 0.

Leaves (parameter ``leaf``): ``"uniform"`` places the point uniformly in the
leaf cell; ``"bilinear"`` warps it by the bilinear interpolant of max(f, 0) at
the leaf's four corners (Mitsuba's ``square_to_bilinear``), which follows the
lobe's slope inside the leaf. Either way the pdf is (product of branch
probabilities) x (leaf density) / (leaf solid angle): exact for the warp.

Frame: the SH frame itself (z-up); directions and densities are per unit
solid angle in that frame.
"""

from __future__ import annotations

import functools
import math
from typing import NamedTuple

import drjit as dr
import mitsuba as mi

from ..grid import Cell, child_phi_centres, grid_coordinates, grid_direction
from ..sh.basis import as_coefficients, bands_of, sh_eval_sum_on_circle
from ..sh.integrals import (constant_antiderivatives, contract_phi, contract_z, legendre_antiderivatives,
                            phi_integrals_centred)
from ..sh.zonal import RotatedZonalLobes
from .hierarchy import Split, check_depth, check_leaf, leaf_density, sample_leaf, walk_pdf, walk_sample

DEFAULT_DEPTH = 8


CONSTANT_ROW_LEVELS = 3
"""Levels whose cells' bounds-only values are picked from host-computed rows (see
:class:`SHCellWeights`)."""


class ConstantLevel(NamedTuple):
    """Host-computed values of one of the top levels, per cell row iz or column iphi."""

    f_mid: dict
    """(l, m) -> antiderivative at each row's z midpoint."""
    z_lo: dict
    """(l, m) -> z-integral row of each row's lower half (midpoint minus lower bound)."""
    phi_left: list
    """Per index m + order: phi integral over each column's left half."""
    phi_right: list
    centres: tuple
    """(cos, sin) of each column's left, then right half's centre."""


@functools.lru_cache(maxsize=None)
def constant_level(level: int, order: int) -> ConstantLevel:
    """The values :class:`SHCellWeights` selects on a top level, in float64 (as Python
    floats), for the 2^level rows and columns of cells."""
    cells = 2 ** level
    lower = [constant_antiderivatives(-1.0 + 2 * j / cells, order) for j in range(cells)]
    middle = [constant_antiderivatives(-1.0 + (2 * j + 1) / cells, order) for j in range(cells)]
    h = math.pi / 2 ** (level + 1)
    # Column j spans [2 pi j, 2 pi (j + 1)] / 2^level; its halves' centres are c -+ h.
    centres = [(2 * j + 1) * math.pi / cells for j in range(cells)]
    left = [phi_integrals_centred(math.cos(c - h), math.sin(c - h), h, order) for c in centres]
    right = [phi_integrals_centred(math.cos(c + h), math.sin(c + h), h, order) for c in centres]
    return ConstantLevel(
        {k: [row[k] for row in middle] for k in middle[0]},
        {k: [mid[k] - low[k] for mid, low in zip(middle, lower)] for k in middle[0]},
        [[row[i] for row in left] for i in range(2 * order + 1)],
        [[row[i] for row in right] for i in range(2 * order + 1)],
        tuple([f(c + sign * h) for c in centres] for sign in (-1, 1) for f in (math.cos, math.sin)))


class SHCellState(NamedTuple):
    """What :class:`SHCellWeights` carries down the tree for the current cell."""

    f_lo: dict
    """Legendre antiderivative row at the cell's lower z bound, keyed (l, m)."""
    a_cell: list
    """z-contraction A[m] = sum_l f_l^m K~ I_l^|m| of the whole cell, m = -order..order."""
    cos_c: mi.Float
    sin_c: mi.Float
    """cos / sin of the cell's phi centre."""


class SHCellSplit(NamedTuple):
    """Values of :meth:`SHCellWeights.children` that :meth:`~SHCellWeights.advance` reuses."""

    f_mid: dict
    a_lo: list
    a_hi: list
    centres: tuple
    """(cos, sin) of the left and of the right children's phi centres."""


class SHCellWeights:
    """Quadtree weight provider: integrals of an SH expansion over the four children.

    The expansion is a coefficient list or, as the integrators build their lobes,
    :class:`~mitsuba_shsampling.sh.zonal.RotatedZonalLobes`, whose contractions
    over l cost about half (:func:`lobe_bands` gives the band count of either).

    State (:class:`SHCellState`): the antiderivative row at the cell's lower z
    bound, the z-contraction A[m] of the whole cell and cos/sin of the cell's
    phi centre.

    On the top :data:`CONSTANT_ROW_LEVELS` levels a cell is one of 2^k x 2^k
    with the same bounds in every lane, so what depends on the bounds alone is
    selected among values computed once on the host in float64 (at most 3
    selects per entry, :func:`constant_level`) instead of computed per lane:
    the lower child's z-integral row (no Legendre recurrence, no subtraction of
    the carried row) and the children's phi integrals (no recurrence on the
    carried centre). The carried row and centre are then only formed where a
    deeper level needs them (Dr.Jit traces nothing else).
    """

    def __init__(self, coeffs):
        self.coeffs = coeffs
        self.order = lobe_bands(coeffs) - 1
        # Root rows are constants: evaluate them once in float64 on the host.
        lo = constant_antiderivatives(-1.0, self.order)
        hi = constant_antiderivatives(1.0, self.order)
        self._root_lo = {k: mi.Float(v) for k, v in lo.items()}
        self._root_cell = self._contract_z({k: hi[k] - lo[k] for k in hi})

    def _contract_z(self, zint: dict) -> list:
        """A[m] = sum_l f_l^m zint[l, |m|]: factored for rotated zonal lobes."""
        if isinstance(self.coeffs, RotatedZonalLobes):
            return self.coeffs.contract_z(zint, self.order)
        return contract_z(self.coeffs, zint, self.order)

    def root(self) -> SHCellState:
        # The root spans [0, 2 pi): centre pi.
        return SHCellState(self._root_lo, self._root_cell, mi.Float(-1.0), mi.Float(0.0))

    def children(self, state: SHCellState, cell: Cell) -> Split:
        if cell.level < CONSTANT_ROW_LEVELS:
            level = constant_level(cell.level, self.order)

            def pick(values, index):
                """values[index] per lane, from per-cell Python floats."""
                out = mi.Float(values[0])
                for j in range(1, len(values)):
                    out = dr.select(index == j, values[j], out)
                return out

            f_mid = {k: pick(v, cell.iz) for k, v in level.f_mid.items()}
            z_lo = {k: pick(v, cell.iz) for k, v in level.z_lo.items()}
            left = [pick(v, cell.iphi) for v in level.phi_left]
            right = [pick(v, cell.iphi) for v in level.phi_right]
            centres = tuple(pick(v, cell.iphi) for v in level.centres)
        else:
            f_mid = legendre_antiderivatives(cell.zm, self.order)
            z_lo = {k: f_mid[k] - state.f_lo[k] for k in f_mid}
            centres = child_phi_centres(state.cos_c, state.sin_c, cell.level)
            h = math.pi / 2 ** (cell.level + 1)
            left = phi_integrals_centred(centres[0], centres[1], h, self.order)
            right = phi_integrals_centred(centres[2], centres[3], h, self.order)
        a_lo = self._contract_z(z_lo)
        a_hi = [ac - al for ac, al in zip(state.a_cell, a_lo)]
        weights = (contract_phi(a_lo, left), contract_phi(a_lo, right),
                   contract_phi(a_hi, left), contract_phi(a_hi, right))
        return Split(weights, SHCellSplit(f_mid, a_lo, a_hi, centres))

    def advance(self, state: SHCellState, pending: SHCellSplit, cell: Cell, a, b) -> SHCellState:
        cos_l, sin_l, cos_r, sin_r = pending.centres
        return SHCellState(
            {k: dr.select(a, pending.f_mid[k], v) for k, v in state.f_lo.items()},
            [dr.select(a, hi, lo) for lo, hi in zip(pending.a_lo, pending.a_hi)],
            dr.select(b, cos_r, cos_l),
            dr.select(b, sin_r, sin_l))


def lobe_bands(lobe) -> int:
    """Bands of an SH lobe given as coefficients or as :class:`RotatedZonalLobes`."""
    return lobe.n_bands if isinstance(lobe, RotatedZonalLobes) else bands_of(lobe)


def as_lobe(lobe):
    """A lobe as the warps take it: :class:`RotatedZonalLobes` as it is, anything
    else as a coefficient list (:func:`~mitsuba_shsampling.sh.basis.as_coefficients`)."""
    return lobe if isinstance(lobe, RotatedZonalLobes) else as_coefficients(lobe)


def sh_leaf_corners(coeffs: list):
    """The SH function's values at a leaf's corners, for bilinear leaves."""
    def corners(leaf: Cell):
        return (sh_eval_sum_on_circle(coeffs, leaf.z0, [leaf.phi0, leaf.phi1])
                + sh_eval_sum_on_circle(coeffs, leaf.z1, [leaf.phi0, leaf.phi1]))
    return corners


class SHWarp:
    """Hierarchical sample warping of the non-negative part of an SH function.

    Parameter ``depth`` (int, default 8):
        Number of 2x2 levels; the leaves are 2^depth x 2^depth equal-area
        cells. float32 samples support depth <= 12 (see :mod:`.hierarchy`).

    Parameter ``leaf`` (str, default ``"uniform"``):
        ``"uniform"`` or ``"bilinear"`` placement inside the leaf.

    ``sample(coeffs, u)`` and ``pdf(coeffs, d)`` take ``coeffs`` as a list of
    n^2 per-lane ``mi.Float`` (or Python floats shared by all lanes), SH
    index l(l+1)+m, and return solid-angle densities of max(f, 0)'s warp.
    Lanes whose function has no positive mass (or non-finite coefficients)
    get pdf 0 and the unit direction +z (a constant: no warp is spent on
    a sample that carries no weight).
    """

    def __init__(self, depth: int = DEFAULT_DEPTH, leaf: str = "uniform"):
        self.depth = check_depth(depth)
        self.leaf = check_leaf(leaf)

    def sample(self, coeffs, u: mi.Point2f):
        """Warp ``u`` in [0,1)^2 to a direction; returns (direction, pdf)."""
        coeffs = as_coefficients(coeffs)
        leaf, t, prob, valid, _ = walk_sample(SHCellWeights(coeffs), self.depth, u)
        z, phi, density = sample_leaf(self.leaf, leaf, t, sh_leaf_corners(coeffs))
        d = dr.select(valid, grid_direction(z, phi), mi.Vector3f(0.0, 0.0, 1.0))
        return d, dr.select(valid, prob * density / leaf.area, 0.0)

    def pdf(self, coeffs, d: mi.Vector3f) -> mi.Float:
        """Density (per steradian) with which :meth:`sample` produces ``d``."""
        coeffs = as_coefficients(coeffs)
        z, phi = grid_coordinates(d)
        leaf, _, prob, _ = walk_pdf(SHCellWeights(coeffs), self.depth, z, phi)
        return prob * leaf_density(self.leaf, leaf, z, phi, sh_leaf_corners(coeffs)) / leaf.area
