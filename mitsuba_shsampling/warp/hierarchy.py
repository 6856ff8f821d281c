"""The hierarchical walks every warp is built from: sampling and pdf in one place.

Hierarchical sample warping (Clarberg et al. 2005) descends a tree over the
equal-area grid of :mod:`mitsuba_shsampling.grid`. At each level a *weight
provider* returns the child weights of the current cell; sampling picks a
child in proportion to them and rescales the uniform sample, the pdf walk picks
the child that holds a given point. Both multiply the same branch
probabilities, so

    pdf(omega) = prod(branch probabilities) * leaf_density(t) / leaf_area

is the exact density of the warp whatever the provider returns (clamping,
approximations, float rounding): safe for MIS. Two trees exist:

- :func:`walk_sample` / :func:`walk_pdf`: a quadtree, four children (a, b) =
  (0,0), (0,1), (1,0), (1,1) per cell, a the z half, b the phi half
  (:class:`QuadWeights` providers); the z half is chosen from the row sums,
  then the phi half within the chosen row;
- :func:`walk_sample_absolute` / :func:`walk_pdf_absolute`: the quadtree for
  providers whose weights are the children's absolute probabilities (they sum
  to the parent's), which telescope: no clamp, no per-level probability;
- :func:`walk_sample_1d` / :func:`walk_pdf_1d`: a binary tree over an
  interval (:class:`BinaryWeights` providers), for warps that split z and phi
  separately.

Below a provider's own levels an *additive* pyramid (children sum to the
parent, e.g. an environment's) can finish the walk:
:func:`descend_pyramid_sample` / :func:`descend_pyramid_pdf`, whose branch
probabilities telescope to leaf / cell. Inside the leaf the point is placed by
:func:`sample_leaf`, whose density :func:`leaf_density` returns.

The contract of a provider (the protocols below): ``root()`` gives the state of
the root cell; ``children(state, ...)`` gives a :class:`Split`, the child
weights and whatever ``advance`` needs besides the state (computed once, for
both); ``advance(state, pending, ..., choice)`` gives the state of the chosen
child. States and pending values are the provider's own (typed) values; the
walks only pass them on.

The rescaled sample loses about one bit per split and dimension, so 24-bit
float32 samples support ~10-12 levels with useful leaf resolution left.
"""

from __future__ import annotations

from typing import Any, Callable, NamedTuple, Protocol

import drjit as dr
import mitsuba as mi

from ..grid import Cell, interval

MAX_DEPTH = 12
"""Deepest tree float32 samples can drive (one bit per level and dimension)."""

LAST_BELOW_ONE = 0.99999994
"""Largest float32 below 1: rescaled samples are kept in [0, 1)."""

LEAF_KINDS = ("uniform", "bilinear")


def check_depth(depth) -> int:
    if isinstance(depth, bool) or not isinstance(depth, int):
        raise TypeError(f"warp depth must be an int, got {depth!r}")
    if not 0 <= depth <= MAX_DEPTH:
        raise ValueError(
            f"warp depth must be in [0, {MAX_DEPTH}] (float32 samples lose one bit per level), got {depth}")
    return depth


def check_leaf(leaf, kinds: tuple = LEAF_KINDS) -> str:
    """Validate a warp's ``leaf`` parameter against the placements it offers."""
    if leaf not in kinds:
        raise ValueError(f"leaf must be one of {kinds}, got {leaf!r}")
    return leaf


class Split(NamedTuple):
    """What a provider's ``children`` returns."""

    weights: tuple
    """Child weights (4 for a quadtree, lower/upper for a binary tree); clamped at 0 by the walks."""
    pending: Any
    """Provider data computed with the weights that ``advance`` needs (None if nothing)."""


class QuadWeights(Protocol):
    """Weight provider of :func:`walk_sample` / :func:`walk_pdf`."""

    def root(self) -> Any: ...

    def children(self, state: Any, cell: Cell) -> Split: ...

    def advance(self, state: Any, pending: Any, cell: Cell, a: mi.Bool, b: mi.Bool) -> Any: ...


class BinaryWeights(Protocol):
    """Weight provider of :func:`walk_sample_1d` / :func:`walk_pdf_1d`; the cell
    is given by its level and bounds (lower, middle, upper)."""

    def root(self) -> Any: ...

    def children(self, state: Any, level: int, lo: mi.Float, mid: mi.Float, hi: mi.Float) -> Split: ...

    def advance(self, state: Any, pending: Any, level: int, upper: mi.Bool) -> Any: ...


def _clamped(w):
    """A child weight clamped at 0 (NaN to 0)."""
    return dr.select(w > 0, w, 0.0)


def _split_absolute(w_lo, w_hi, u):
    """One binary split driven by the sample ``u`` in [0, 1): (upper half chosen,
    its weight, ``u`` rescaled into it). One division, for the rescaled sample;
    the probability is not divided out (:func:`walk_sample_absolute` needs none,
    :func:`_split_sample` divides once more)."""
    # In units of weight: u * total is the sample's position in [0, total).
    # The next level waits for the choice, which then needs no division, and
    # the rescaled sample (position - lower bound) / chosen weight is
    # (u - p_lo) / p_chosen with one division instead of two. Rounding can
    # put it a hair outside [0, 1): the clip keeps it in.
    position = u * (w_lo + w_hi)
    upper = position >= w_lo
    chosen = dr.select(upper, w_hi, w_lo)
    return upper, chosen, dr.clip((position - dr.select(upper, w_lo, 0.0)) / chosen, 0.0, LAST_BELOW_ONE)


def _split_sample(w_lo, w_hi, u):
    """One binary split of clamped weights driven by the sample ``u`` in [0, 1).

    Returns (upper half chosen, probability of the chosen half, ``u``
    rescaled into the chosen half, finite total). Where both weights vanish
    the probability is NaN, and so becomes the product of a walk through that
    split: the walks test the product once at the end instead of the total at
    every level.
    """
    upper, chosen, u = _split_absolute(w_lo, w_hi, u)
    total = w_lo + w_hi
    # The chosen weight over the total, not 1 - p_lo for the upper half: that
    # keeps a small upper half's digits (1 - p_lo is off by up to 3e-8 absolute).
    return upper, chosen / total, u, total < dr.inf


def _split_probability(w_lo, w_hi, upper):
    """Probability with which :func:`_split_sample` chooses the half ``upper``
    (NaN where both weights vanish, 0 where the total is not finite)."""
    total = w_lo + w_hi
    return dr.select(total < dr.inf, dr.select(upper, w_hi, w_lo) / total, 0.0)


def select_child(w, a, b):
    """Entry (a, b) of four per-child values ordered (0,0), (0,1), (1,0), (1,1)."""
    return dr.select(a, dr.select(b, w[3], w[2]), dr.select(b, w[1], w[0]))


# ------------------------------------------------------------------ quadtree

def walk_sample(provider: QuadWeights, depth: int, u: mi.Point2f):
    """Descend ``depth`` levels choosing children with the sample ``u``.

    Returns (leaf cell, rescaled sample in the leaf, probability of the leaf,
    valid mask, provider state at the leaf). The probability underflows to 0
    (an invalid sample, with pdf 0 in :func:`walk_pdf` too) only below 1e-38.
    """
    iz, iphi = mi.UInt32(0), mi.UInt32(0)
    prob, valid = mi.Float(1.0), mi.Bool(True)
    uz, uphi = dr.clip(u.x, 0.0, LAST_BELOW_ONE), dr.clip(u.y, 0.0, LAST_BELOW_ONE)
    state = provider.root()
    for level in range(depth):
        cell = Cell(level, iz, iphi)
        split = provider.children(state, cell)
        w = [_clamped(wi) for wi in split.weights]
        # A finite row total makes every weight, and so the column total, finite.
        a, p_row, uz, finite = _split_sample(w[0] + w[1], w[2] + w[3], uz)
        b, p_column, uphi, _ = _split_sample(dr.select(a, w[2], w[0]), dr.select(a, w[3], w[1]), uphi)
        valid &= finite
        prob *= p_row * p_column
        state = provider.advance(state, split.pending, cell, a, b)
        iz = 2 * iz + dr.select(a, 1, 0)
        iphi = 2 * iphi + dr.select(b, 1, 0)
    return Cell(depth, iz, iphi), mi.Point2f(uz, uphi), prob, valid & (prob > 0), state


def _walk_to_point(provider: QuadWeights, depth: int, z, phi, branch: Callable):
    """The pdf walks' descent towards (z, phi): per level the provider's split, the
    child (a, b) holding the point, and ``prob = branch(prob, weights, a, b)``.

    Returns (leaf cell, prob, provider state at the leaf)."""
    iz, iphi = mi.UInt32(0), mi.UInt32(0)
    prob = mi.Float(1.0)
    state = provider.root()
    for level in range(depth):
        cell = Cell(level, iz, iphi)
        split = provider.children(state, cell)
        a, b = z >= cell.zm, phi >= cell.phim
        prob = branch(prob, split.weights, a, b)
        state = provider.advance(state, split.pending, cell, a, b)
        iz = 2 * iz + dr.select(a, 1, 0)
        iphi = 2 * iphi + dr.select(b, 1, 0)
    return Cell(depth, iz, iphi), prob, state


def walk_pdf(provider: QuadWeights, depth: int, z, phi):
    """Descend ``depth`` levels towards the point (z, phi).

    Returns (leaf cell, position of the point in the leaf in [0,1]^2,
    probability of the leaf, provider state at the leaf).
    """
    def branch(prob, weights, a, b):
        w = [_clamped(wi) for wi in weights]
        return prob * (_split_probability(w[0] + w[1], w[2] + w[3], a)
                       * _split_probability(dr.select(a, w[2], w[0]), dr.select(a, w[3], w[1]), b))

    leaf, prob, state = _walk_to_point(provider, depth, z, phi, branch)
    t = mi.Point2f(dr.clip((z - leaf.z0) * (1.0 / leaf.dz), 0.0, 1.0),
                   dr.clip((phi - leaf.phi0) * (1.0 / leaf.dphi), 0.0, 1.0))
    return leaf, t, dr.select(prob > 0, prob, 0.0), state


def _quad_split(w, uz, uphi):
    """Choose one of four absolute weights (order (0,0), (0,1), (1,0), (1,1)):
    the z half by the row sums, then the phi half within the row. Returns
    (a, b, rescaled uz, rescaled uphi, the chosen weight)."""
    a, _, uz = _split_absolute(w[0] + w[1], w[2] + w[3], uz)
    b, chosen, uphi = _split_absolute(dr.select(a, w[2], w[0]), dr.select(a, w[3], w[1]), uphi)
    return a, b, uz, uphi, chosen


def walk_sample_absolute(provider: QuadWeights, depth: int, u: mi.Point2f):
    """:func:`walk_sample` for a provider whose weights are *absolute*: each
    child's probability of being reached, finite and non-negative, the four
    summing to their parent's (1 at the root), e.g. a mixture of hierarchical
    distributions (:class:`~.product.ProductWeights`).

    The branch probabilities then telescope: the leaf's probability is its own
    weight, up to the rounding of the sums (~1e-7 relative per level). So no
    weight is clamped and no probability divided out at each split: one
    division per split, for the rescaled sample, against two and the clamps
    of the generic walk. :func:`walk_pdf_absolute` returns the same weight.
    """
    iz, iphi = mi.UInt32(0), mi.UInt32(0)
    uz, uphi = dr.clip(u.x, 0.0, LAST_BELOW_ONE), dr.clip(u.y, 0.0, LAST_BELOW_ONE)
    prob = mi.Float(1.0)
    state = provider.root()
    for level in range(depth):
        cell = Cell(level, iz, iphi)
        split = provider.children(state, cell)
        a, b, uz, uphi, prob = _quad_split(split.weights, uz, uphi)
        state = provider.advance(state, split.pending, cell, a, b)
        iz = 2 * iz + dr.select(a, 1, 0)
        iphi = 2 * iphi + dr.select(b, 1, 0)
    return Cell(depth, iz, iphi), mi.Point2f(uz, uphi), prob, prob > 0, state


def walk_pdf_absolute(provider: QuadWeights, depth: int, z, phi):
    """:func:`walk_pdf` for the providers of :func:`walk_sample_absolute`: the
    weight of the leaf holding (z, phi). Only the last level's weights are
    used (Dr.Jit traces none of the others); the levels above only carry the
    provider's state down.

    Returns (leaf cell, probability of the leaf, provider state at the leaf).
    """
    return _walk_to_point(provider, depth, z, phi, lambda prob, weights, a, b: select_child(weights, a, b))


# --------------------------------------------------------------- binary tree

def walk_sample_1d(provider: BinaryWeights, depth: int, u, x0: float, x1: float):
    """Binary-tree version of :func:`walk_sample` over the interval [x0, x1].

    Returns (leaf index, rescaled sample, leaf probability, valid mask,
    provider state at the leaf); leaf i covers [x0 + i w, x0 + (i+1) w],
    w = (x1 - x0) / 2^depth.
    """
    index, prob, valid = mi.UInt32(0), mi.Float(1.0), mi.Bool(True)
    u = dr.clip(u, 0.0, LAST_BELOW_ONE)
    state = provider.root()
    # The cell's lower bound is carried (a select and an add after each
    # choice) rather than rebuilt from the index (a conversion and a
    # multiply-add): the next level's weights wait for it.
    lo = x0
    for level in range(depth):
        half = (x1 - x0) / 2 ** (level + 1)
        mid = lo + half
        split = provider.children(state, level, lo, mid, mid + half)
        upper, p, u, finite = _split_sample(*(_clamped(w) for w in split.weights), u)
        prob *= p
        valid &= finite
        state = provider.advance(state, split.pending, level, upper)
        lo = dr.select(upper, mid, lo)
        index = 2 * index + dr.select(upper, 1, 0)
    return index, u, prob, valid & (prob > 0), state


def walk_pdf_1d(provider: BinaryWeights, depth: int, x, x0: float, x1: float):
    """Binary-tree version of :func:`walk_pdf`: descend towards ``x`` in [x0, x1].

    Returns (leaf index, leaf probability, provider state at the leaf).
    """
    index, prob = mi.UInt32(0), mi.Float(1.0)
    state = provider.root()
    for level in range(depth):
        lo, mid, hi = interval(level, index, x0, x1)
        split = provider.children(state, level, lo, mid, hi)
        upper = x >= mid
        prob *= _split_probability(*(_clamped(w) for w in split.weights), upper)
        state = provider.advance(state, split.pending, level, upper)
        index = 2 * index + dr.select(upper, 1, 0)
    return index, dr.select(prob > 0, prob, 0.0), state


# ------------------------------------------------ additive pyramid, telescoped

def descend_pyramid_sample(pyramid, cell: Cell, u: mi.Point2f, depth: int | None = None):
    """Continue a walk from ``cell`` down to level ``depth`` (default: the finest,
    D) of an *additive* pyramid (every cell's integral is the sum of its four
    children's, e.g. :class:`~mitsuba_shsampling.envmap.pyramid.EnvPyramid`),
    choosing children in proportion to their integrals with the sample ``u``.

    Returns (leaf cell, rescaled sample in the leaf, P(leaf | cell)). The
    branch probabilities telescope to leaf integral / cell integral, so no
    product is carried down; :func:`descend_pyramid_pdf` evaluates the same
    probability for a given point. Weights of a cell reached with positive
    probability are finite and non-negative with a positive sum, so unlike
    :func:`walk_sample` no clamping is needed, and the splits are those of
    :func:`walk_sample_absolute` (one division each).

    The descent to D is a loop bounded by the pyramid's device value of D
    (``finest_level``), its last split read from the leaf records: one kernel
    serves every map deeper than ``cell``'s level + 1, whatever its depth.
    """
    to_leaves = depth is None or depth == pyramid.depth
    if cell.level >= (pyramid.depth if to_leaves else depth):
        return cell, u, mi.Float(1.0)
    start = cell.level
    stop = pyramid.finest_level - 1 if to_leaves else depth  # the buffer's levels end there

    def split(w, level, iz, iphi, uz, uphi, cell_integral):
        cell_integral = dr.select(level == start, (w[0] + w[1]) + (w[2] + w[3]), cell_integral)
        a, b, uz, uphi, chosen = _quad_split(w, uz, uphi)
        return level + 1, 2 * iz + dr.select(a, 1, 0), 2 * iphi + dr.select(b, 1, 0), uz, uphi, cell_integral, chosen

    def descend(level, iz, iphi, uz, uphi, cell_integral, _):
        return split(pyramid.block_children(level, iz, iphi), level, iz, iphi, uz, uphi, cell_integral)

    state = (mi.UInt32(start), mi.UInt32(cell.iz), mi.UInt32(cell.iphi), mi.Float(u.x), mi.Float(u.y),
             mi.Float(1.0), mi.Float(1.0))
    state = dr.while_loop(state, lambda level, *_: level < stop, descend)
    if not to_leaves:
        _, iz, iphi, uz, uphi, cell_integral, leaf_integral = state
        return Cell(depth, iz, iphi), mi.Point2f(uz, uphi), leaf_integral / cell_integral
    _, iz, iphi, uz, uphi, cell_integral, leaf_integral = split(pyramid.leaf_children(*state[1:3]), *state[:6])
    return pyramid.leaf_cell(iz, iphi), mi.Point2f(uz, uphi), leaf_integral / cell_integral


def descend_pyramid_pdf(pyramid, cell: Cell, z, phi, depth: int | None = None):
    """P(leaf | cell) of :func:`descend_pyramid_sample` for the leaf holding
    (z, phi), and that leaf. The leaf is found by comparisons with the cells'
    midpoints, as the walks do (no gathers; the cells' extents halve exactly
    from level to level, so the midpoints are those of :class:`~..grid.Cell`);
    two gathers give the integrals."""
    to_leaves = depth is None or depth == pyramid.depth
    if cell.level >= (pyramid.depth if to_leaves else depth):
        return cell, mi.Float(1.0)
    stop = pyramid.finest_level if to_leaves else depth

    def descend(level, iz, iphi, dz, dphi):
        zm = dr.fma(mi.Float(iz), dz, -1.0) + 0.5 * dz
        phim = mi.Float(iphi) * dphi + 0.5 * dphi
        return (level + 1, 2 * iz + dr.select(z >= zm, 1, 0), 2 * iphi + dr.select(phi >= phim, 1, 0),
                0.5 * dz, 0.5 * dphi)

    state = (mi.UInt32(cell.level), mi.UInt32(cell.iz), mi.UInt32(cell.iphi), mi.Float(cell.dz), mi.Float(cell.dphi))
    _, iz, iphi, _, _ = dr.while_loop(state, lambda level, *_: level < stop, descend)
    if to_leaves:
        leaf, inside = pyramid.leaf_cell(iz, iphi), pyramid.leaf_integral(iz, iphi)
    else:
        leaf, inside = Cell(depth, iz, iphi), pyramid.cell_integral(depth, iz, iphi)
    parent = pyramid.cell_integral(cell.level, cell.iz, cell.iphi)
    return leaf, dr.select(parent > 0, inside / dr.select(parent > 0, parent, 1.0), 0.0)


# ---------------------------------------------------------------------- leaf

LeafCorners = Callable[[Cell], list]
"""Non-negative function values at a leaf's corners (z0 phi0, z0 phi1, z1 phi0, z1 phi1)."""


def _bilinear_corners(corners: LeafCorners, leaf: Cell):
    """Corner values as Mitsuba's bilinear warp wants them (x = phi, y = z,
    mean 1); all ones (uniform) where they vanish or are not finite."""
    v = [dr.maximum(c, 0.0) for c in corners(leaf)]
    total = (v[0] + v[1]) + (v[2] + v[3])
    flat = ~(dr.isfinite(total) & (total > 0))
    scale = 4.0 / dr.select(flat, 1.0, total)
    return [dr.select(flat, 1.0, c * scale) for c in v]


def sample_leaf(leaf_kind: str, leaf: Cell, t: mi.Point2f, corners: LeafCorners | None = None):
    """Place the rescaled sample ``t`` = (t_z, t_phi) in the leaf cell:
    uniformly, or (``"bilinear"``) by the bilinear interpolant of the
    ``corners`` values (Mitsuba's ``square_to_bilinear``).

    Returns (z, phi, density w.r.t. the leaf's unit square).
    """
    if leaf_kind == "bilinear":
        p, density = mi.warp.square_to_bilinear(*_bilinear_corners(corners, leaf), mi.Point2f(t.y, t.x))
        t = mi.Point2f(p.y, p.x)
    else:
        density = mi.Float(1.0)
    return dr.lerp(leaf.z0, leaf.z1, t.x), dr.lerp(leaf.phi0, leaf.phi1, t.y), density


def leaf_density(leaf_kind: str, leaf: Cell, z, phi, corners: LeafCorners | None = None):
    """Density of :func:`sample_leaf` at (z, phi) w.r.t. the leaf's unit square."""
    if leaf_kind != "bilinear":
        return mi.Float(1.0)
    t_z = dr.clip((z - leaf.z0) * (1.0 / leaf.dz), 0.0, 1.0)
    t_phi = dr.clip((phi - leaf.phi0) * (1.0 / leaf.dphi), 0.0, 1.0)
    return mi.warp.square_to_bilinear_pdf(*_bilinear_corners(corners, leaf), mi.Point2f(t_phi, t_z))


# The separable linear leaf (:class:`~.strip_hsw.SHStripWarp`'s ``"linear"``): each
# coordinate of the leaf placed by the linear interpolant of two end values, which a
# warp gets for O(n) where the four corner values of ``"bilinear"`` cost O(n^2) each.

def _linear_ends(ends):
    """Two end values clamped at 0; (1, 1) (uniform) where they vanish or are not finite."""
    v0, v1 = (dr.maximum(v, 0.0) for v in ends)
    total = v0 + v1
    flat = ~(dr.isfinite(total) & (total > 0))
    return dr.select(flat, 1.0, v0), dr.select(flat, 1.0, v1)


def _linear_density(v0, v1, x):
    """Density on [0, 1] of the normalised linear interpolant of (v0, v1) at ``x``."""
    return 2.0 * dr.lerp(v0, v1, x) / (v0 + v1)


def sample_linear_leaf(leaf: Cell, t: mi.Point2f, z_ends, phi_ends):
    """Place ``t`` = (t_z, t_phi) in the leaf, each coordinate by the linear
    interpolant of its two end values (at z0, z1 and at phi0, phi1;
    Mitsuba's ``interval_to_linear``). Returns (z, phi, density w.r.t. the leaf's unit square)."""
    a0, a1 = _linear_ends(z_ends)
    b0, b1 = _linear_ends(phi_ends)
    x, y = mi.warp.interval_to_linear(a0, a1, t.x), mi.warp.interval_to_linear(b0, b1, t.y)
    x, y = dr.clip(x, 0.0, 1.0), dr.clip(y, 0.0, 1.0)
    density = _linear_density(a0, a1, x) * _linear_density(b0, b1, y)
    return dr.lerp(leaf.z0, leaf.z1, x), dr.lerp(leaf.phi0, leaf.phi1, y), density


def linear_leaf_density(leaf: Cell, z, phi, z_ends, phi_ends):
    """Density of :func:`sample_linear_leaf` at (z, phi) w.r.t. the leaf's unit square."""
    a0, a1 = _linear_ends(z_ends)
    b0, b1 = _linear_ends(phi_ends)
    x = dr.clip((z - leaf.z0) * (1.0 / leaf.dz), 0.0, 1.0)
    y = dr.clip((phi - leaf.phi0) * (1.0 / leaf.dphi), 0.0, 1.0)
    return _linear_density(a0, a1, x) * _linear_density(b0, b1, y)
