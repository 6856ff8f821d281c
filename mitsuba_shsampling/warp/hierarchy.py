"""The hierarchical walk shared by every warp: sampling and pdf in one place.

Hierarchical sample warping (Clarberg et al. 2005) descends a 2x2 tree over
the equal-area cylinder (z, phi) in [-1, 1] x [0, 2 pi). At each level a
*weight provider* returns the four child weights of the current cell, ordered
(a, b) = (0,0), (0,1), (1,0), (1,1) with a the z-half and b the phi-half;
weights are clamped at 0. Sampling picks the z-half from the row sums and the
phi-half from the chosen row, rescaling the uniform sample each time; the pdf
walk picks the child that contains a given point. Both multiply the same
branch probabilities, so

    pdf(omega) = prod(branch probabilities) * leaf_density(t) / leaf_area

is the exact density of the warp whatever the provider returns (clamping,
approximations, float rounding of the weights): safe for MIS.

The rescaled sample loses about one bit per split and dimension, so 24-bit
float32 samples support ~10-12 levels with useful leaf resolution left.
"""

from __future__ import annotations

import math

import drjit as dr
import mitsuba as mi

TWO_PI = 2.0 * math.pi
MAX_DEPTH = 12
"""Deepest tree float32 samples can drive (one bit per level and dimension)."""


def check_depth(depth) -> int:
    if isinstance(depth, bool) or not isinstance(depth, int):
        raise TypeError(f"warp depth must be an int, got {depth!r}")
    if not 0 <= depth <= MAX_DEPTH:
        raise ValueError(
            f"warp depth must be in [0, {MAX_DEPTH}] (float32 samples lose one bit per level), got {depth}")
    return depth


class Cell:
    """Bounds of the current cell of every lane at one level."""

    def __init__(self, level: int, iz, iphi):
        self.level, self.iz, self.iphi = level, iz, iphi
        dz, dphi = 2.0 / 2**level, TWO_PI / 2**level
        self.z0 = dr.fma(mi.Float(iz), dz, -1.0)
        self.z1 = self.z0 + dz
        self.zm = self.z0 + 0.5 * dz
        self.phi0 = mi.Float(iphi) * dphi
        self.phi1 = self.phi0 + dphi
        self.phim = self.phi0 + 0.5 * dphi
        self.area = dz * dphi


def grid_direction(z, phi) -> mi.Vector3f:
    """Unit direction (z-up) of cylinder coordinates (z, phi)."""
    s = dr.safe_sqrt(dr.fma(-z, z, 1.0))
    sin_phi, cos_phi = dr.sincos(phi)
    return mi.Vector3f(s * cos_phi, s * sin_phi, z)


def grid_coordinates(d: mi.Vector3f):
    """(z, phi) of a direction; normalises ``d``.

    phi = atan2(y, x) wrapped into [0, 2 pi]; at the poles phi = 0. A tiny
    negative angle whose wrap rounds up gives exactly 2 pi: it stays on the
    seam's high side, in the last column, where a sample drawn there came from.
    """
    d = dr.normalize(d)
    z = dr.clip(d.z, -1.0, 1.0)
    phi = dr.atan2(d.y, d.x)
    phi = dr.select(phi < 0, phi + TWO_PI, phi)
    return z, dr.minimum(phi, TWO_PI)


def _normalised_weights(w):
    """Clamp child weights at 0; return them, their total and a validity mask."""
    w = [dr.maximum(dr.select(dr.isnan(wi), 0.0, wi), 0.0) for wi in w]
    total = w[0] + w[1] if len(w) == 2 else (w[0] + w[1]) + (w[2] + w[3])
    valid = dr.isfinite(total) & (total > 0)
    return w, total, valid


def walk_sample(provider, depth: int, u: mi.Point2f):
    """Descend ``depth`` levels choosing children with the sample ``u``.

    Returns (leaf cell, rescaled sample in the leaf, probability of the leaf,
    valid mask, provider state at the leaf).
    """
    iz, iphi = mi.UInt32(0), mi.UInt32(0)
    prob = mi.Float(1.0)
    valid = mi.Bool(True)
    uz, uphi = dr.clip(u.x, 0.0, 1.0), dr.clip(u.y, 0.0, 1.0)
    state = provider.root()
    for level in range(depth):
        cell = Cell(level, iz, iphi)
        w, total, ok = _normalised_weights(provider.children(state, cell))
        valid &= ok
        row_lo = w[0] + w[1]
        p_lo = row_lo / dr.select(ok, total, 1.0)
        a = uz >= p_lo
        uz = dr.select(a, (uz - p_lo) / (1.0 - p_lo), uz / p_lo)
        left, right = dr.select(a, w[2], w[0]), dr.select(a, w[3], w[1])
        row = left + right
        p_left = left / dr.select(row > 0, row, 1.0)
        b = uphi >= p_left
        uphi = dr.select(b, (uphi - p_left) / (1.0 - p_left), uphi / p_left)
        prob *= dr.select(b, right, left) / dr.select(ok, total, 1.0)
        # Rescaling can round to exactly 1 (or NaN for a zero-probability side
        # that is never chosen): keep the sample inside [0, 1).
        uz = dr.clip(dr.select(dr.isfinite(uz), uz, 0.0), 0.0, 0.99999994)
        uphi = dr.clip(dr.select(dr.isfinite(uphi), uphi, 0.0), 0.0, 0.99999994)
        state = provider.advance(state, cell, a, b)
        iz = 2 * iz + dr.select(a, 1, 0)
        iphi = 2 * iphi + dr.select(b, 1, 0)
    return Cell(depth, iz, iphi), mi.Point2f(uz, uphi), prob, valid, state


LAST_BELOW_ONE = 0.99999994
"""Largest float32 below 1: rescaled samples are kept in [0, 1)."""


def descend_pyramid_sample(pyramid, cell: Cell, depth: int, u: mi.Point2f):
    """Continue a walk from ``cell`` down to level ``depth`` of an *additive*
    pyramid (every cell's integral is the sum of its four children's, e.g.
    :class:`~mitsuba_shsampling.envmap.pyramid.EnvPyramid`), choosing children
    in proportion to their integrals with the sample ``u``.

    Returns (leaf cell, rescaled sample in the leaf, P(leaf | cell)). The
    branch probabilities telescope to leaf integral / cell integral, so no
    product is carried down; :func:`descend_pyramid_pdf` evaluates the same
    probability for a given point. Weights of a cell reached with positive
    probability are finite and non-negative with a positive sum, so unlike
    :func:`walk_sample` no clamping is needed: about a third of its work per
    level.
    """
    iz, iphi = cell.iz, cell.iphi
    uz, uphi = u.x, u.y
    cell_integral = leaf_integral = mi.Float(1.0)
    for level in range(cell.level, depth):
        w = pyramid.children(level, iz, iphi)
        row_lo = w[0] + w[1]
        total = row_lo + (w[2] + w[3])
        if level == cell.level:
            cell_integral = total
        p_lo = row_lo / total
        a = uz >= p_lo
        uz = dr.minimum((uz - dr.select(a, p_lo, 0.0)) / dr.select(a, 1.0 - p_lo, p_lo), LAST_BELOW_ONE)
        left, right = dr.select(a, w[2], w[0]), dr.select(a, w[3], w[1])
        p_left = left / (left + right)
        b = uphi >= p_left
        uphi = dr.minimum((uphi - dr.select(b, p_left, 0.0)) / dr.select(b, 1.0 - p_left, p_left), LAST_BELOW_ONE)
        leaf_integral = dr.select(b, right, left)
        iz = 2 * iz + dr.select(a, 1, 0)
        iphi = 2 * iphi + dr.select(b, 1, 0)
    return Cell(depth, iz, iphi), mi.Point2f(uz, uphi), leaf_integral / cell_integral


def descend_pyramid_pdf(pyramid, cell: Cell, depth: int, z, phi):
    """P(leaf | cell) of :func:`descend_pyramid_sample` for the leaf holding
    (z, phi), and that leaf. The leaf is found by comparisons with the cells'
    midpoints, as the walks do (no gathers); two gathers give the integrals."""
    iz, iphi = cell.iz, cell.iphi
    for level in range(cell.level, depth):
        step = Cell(level, iz, iphi)
        iz = 2 * iz + dr.select(z >= step.zm, 1, 0)
        iphi = 2 * iphi + dr.select(phi >= step.phim, 1, 0)
    leaf = Cell(depth, iz, iphi)
    if cell.level == depth:
        return leaf, mi.Float(1.0)
    parent = pyramid.cell_integral(cell.level, cell.iz, cell.iphi)
    inside = pyramid.cell_integral(depth, iz, iphi)
    return leaf, dr.select(parent > 0, inside / dr.select(parent > 0, parent, 1.0), 0.0)


def _choose_half(w_lo, w_hi, u):
    """One binary split driven by the sample ``u`` in [0, 1).

    Returns (upper half chosen, probability of the chosen half, ``u``
    rescaled into the chosen half, valid mask).
    """
    (w_lo, w_hi), total, ok = _normalised_weights((w_lo, w_hi))
    p_lo = w_lo / dr.select(ok, total, 1.0)
    hi = u >= p_lo
    u = dr.select(hi, (u - p_lo) / (1.0 - p_lo), u / p_lo)
    u = dr.clip(dr.select(dr.isfinite(u), u, 0.0), 0.0, 0.99999994)
    return hi, dr.select(hi, w_hi, w_lo) / dr.select(ok, total, 1.0), u, ok


def walk_sample_1d(provider, depth: int, u, x0: float, x1: float):
    """Binary-tree version of :func:`walk_sample` over the interval [x0, x1].

    ``provider`` has ``root()``, ``children(state, level, lo, mid, hi)``
    returning the two half weights (lower, upper) of the cell [lo, hi], and
    ``advance(state, level, upper)``. Returns (leaf index, rescaled sample,
    leaf probability, valid mask, provider state at the leaf); leaf i covers
    [x0 + i w, x0 + (i+1) w], w = (x1 - x0) / 2^depth.
    """
    index, prob, valid = mi.UInt32(0), mi.Float(1.0), mi.Bool(True)
    u = dr.clip(u, 0.0, 0.99999994)
    state = provider.root()
    for level in range(depth):
        lo, mid, hi = _interval(level, index, x0, x1)
        upper, p, u, ok = _choose_half(*provider.children(state, level, lo, mid, hi), u)
        prob *= p
        valid &= ok
        state = provider.advance(state, level, upper)
        index = 2 * index + dr.select(upper, 1, 0)
    return index, u, prob, valid, state


def walk_pdf_1d(provider, depth: int, x, x0: float, x1: float):
    """Binary-tree version of :func:`walk_pdf`: descend towards ``x`` in [x0, x1].

    Returns (leaf index, leaf probability, provider state at the leaf).
    """
    index, prob = mi.UInt32(0), mi.Float(1.0)
    state = provider.root()
    for level in range(depth):
        lo, mid, hi = _interval(level, index, x0, x1)
        (w_lo, w_hi), total, ok = _normalised_weights(provider.children(state, level, lo, mid, hi))
        upper = x >= mid
        prob *= dr.select(ok, dr.select(upper, w_hi, w_lo) / dr.select(ok, total, 1.0), 0.0)
        state = provider.advance(state, level, upper)
        index = 2 * index + dr.select(upper, 1, 0)
    return index, prob, state


def _interval(level: int, index, x0: float, x1: float):
    """(lower bound, midpoint, upper bound) of cell ``index`` at ``level``."""
    width = (x1 - x0) / 2**level
    lo = dr.fma(mi.Float(index), width, x0)
    return lo, lo + 0.5 * width, lo + width


def walk_pdf(provider, depth: int, z, phi):
    """Descend ``depth`` levels towards the point (z, phi).

    Returns (leaf cell, position of the point in the leaf in [0,1]^2,
    probability of the leaf, provider state at the leaf).
    """
    iz, iphi = mi.UInt32(0), mi.UInt32(0)
    prob = mi.Float(1.0)
    state = provider.root()
    for level in range(depth):
        cell = Cell(level, iz, iphi)
        w, total, ok = _normalised_weights(provider.children(state, cell))
        a, b = z >= cell.zm, phi >= cell.phim
        chosen = dr.select(a, dr.select(b, w[3], w[2]), dr.select(b, w[1], w[0]))
        prob *= dr.select(ok, chosen / dr.select(ok, total, 1.0), 0.0)
        state = provider.advance(state, cell, a, b)
        iz = 2 * iz + dr.select(a, 1, 0)
        iphi = 2 * iphi + dr.select(b, 1, 0)
    leaf = Cell(depth, iz, iphi)
    t = mi.Point2f(dr.clip((z - leaf.z0) / (leaf.z1 - leaf.z0), 0.0, 1.0),
                   dr.clip((phi - leaf.phi0) / (leaf.phi1 - leaf.phi0), 0.0, 1.0))
    return leaf, t, prob, state
