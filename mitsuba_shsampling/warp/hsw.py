"""Hierarchical sample warping of spherical-harmonic functions.

:class:`SHWarp` draws directions distributed like max(f, 0) for an SH
expansion f given per lane (each SIMD lane may carry its own coefficient
vector) and evaluates the exact density of that warp for any direction.

Node weights are analytic integrals of f over (z, phi) cells, computed with
the separable sweep of :mod:`mitsuba_shsampling.sh.integrals`: per level one
row of Legendre antiderivatives at the new z midpoint (the lower bound's row
is carried down the tree), one z-contraction (n^2 multiply-adds) for the lower
half (the upper half is the parent row minus it), and four phi-contractions.
Negative cell integrals (SH ringing) are clamped to probability 0.

Frame: the SH frame itself (z-up); directions and densities are per unit
solid angle in that frame.
"""

from __future__ import annotations

import math

import drjit as dr
import mitsuba as mi
import numpy as np

from ..sh.basis import bands_of
from ..sh.integrals import contract_phi, contract_z, legendre_antiderivatives, phi_integrals
from .hierarchy import check_depth, grid_coordinates, grid_direction, walk_pdf, walk_sample

DEFAULT_DEPTH = 8


def _as_floats(coeffs) -> list:
    bands_of(coeffs)
    return [c if isinstance(c, mi.Float) else mi.Float(c) for c in coeffs]


class SHCellWeights:
    """Weight provider: integrals of an SH expansion over the four children.

    State carried down the tree: the antiderivative row at the cell's lower z
    bound and the z-contraction A[m] of the whole cell.
    """

    def __init__(self, coeffs: list):
        self.coeffs = coeffs
        self.order = bands_of(coeffs) - 1
        # Root rows are constants: evaluate them once in float64 on the host.
        lo = legendre_antiderivatives(-1.0, self.order)
        hi = legendre_antiderivatives(1.0, self.order)
        self._root_lo = {k: mi.Float(float(v)) for k, v in lo.items()}
        self._root_cell = contract_z(coeffs, {k: float(hi[k] - lo[k]) for k in hi}, self.order)

    def root(self):
        return {"f_lo": self._root_lo, "a_cell": self._root_cell}

    def children(self, state, cell):
        f_mid = legendre_antiderivatives(cell.zm, self.order)
        z_lo = {k: f_mid[k] - state["f_lo"][k] for k in f_mid}
        a_lo = contract_z(self.coeffs, z_lo, self.order)
        a_hi = [ac - al for ac, al in zip(state["a_cell"], a_lo)]
        left = phi_integrals(cell.phi0, cell.phim, self.order)
        right = phi_integrals(cell.phim, cell.phi1, self.order)
        state.update(f_mid=f_mid, a_lo=a_lo, a_hi=a_hi)
        return (contract_phi(a_lo, left), contract_phi(a_lo, right),
                contract_phi(a_hi, left), contract_phi(a_hi, right))

    def advance(self, state, cell, a, b):
        return {
            "f_lo": {k: dr.select(a, state["f_mid"][k], v) for k, v in state["f_lo"].items()},
            "a_cell": [dr.select(a, hi, lo) for lo, hi in zip(state["a_lo"], state["a_hi"])],
        }


class SHWarp:
    """Hierarchical sample warping of a non-negative part of an SH function.

    Parameter ``depth`` (int, default 8):
        Number of 2x2 levels; the leaves are 2^depth x 2^depth equal-area
        cells, inside which points are placed uniformly.

    ``sample(coeffs, u)`` and ``pdf(coeffs, d)`` take ``coeffs`` as a list of
    n^2 per-lane ``mi.Float`` (or Python floats shared by all lanes), SH
    index l(l+1)+m, and return solid-angle densities of max(f, 0)'s warp.
    Lanes whose function has no positive mass (or non-finite coefficients)
    get pdf 0 and a harmless unit direction.
    """

    def __init__(self, depth: int = DEFAULT_DEPTH):
        self.depth = check_depth(depth)

    def sample(self, coeffs, u: mi.Point2f):
        """Warp ``u`` in [0,1)^2 to a direction; returns (direction, pdf)."""
        provider = SHCellWeights(_as_floats(coeffs))
        leaf, t, prob, valid, _ = walk_sample(provider, self.depth, u)
        z = dr.lerp(leaf.z0, leaf.z1, t.x)
        phi = dr.lerp(leaf.phi0, leaf.phi1, t.y)
        d = dr.select(valid, grid_direction(z, phi), mi.warp.square_to_uniform_sphere(u))
        return d, dr.select(valid, prob / leaf.area, 0.0)

    def pdf(self, coeffs, d: mi.Vector3f) -> mi.Float:
        """Density (per steradian) with which :meth:`sample` produces ``d``."""
        provider = SHCellWeights(_as_floats(coeffs))
        z, phi = grid_coordinates(d)
        leaf, _, prob, _ = walk_pdf(provider, self.depth, z, phi)
        return prob / leaf.area
