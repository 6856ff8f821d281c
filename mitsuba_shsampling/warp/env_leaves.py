"""Finishing a walk in the environment's pyramid: the descent below a warp's own
levels and the placement inside the leaf, with their densities.

The product warps (:class:`~.product.ProductWarp`, :class:`~.cosine_table.CosineTable`,
the oracle) weight their top levels by a lobe; below them every part of their
mixtures follows the environment, so the pyramid's own cell integrals finish the
walk (:func:`~.hierarchy.descend_pyramid_sample`, telescoped), and inside the
finest cell the point follows the bilinear interpolant of the pyramid's target.
"""

from __future__ import annotations

import drjit as dr
import mitsuba as mi

from ..grid import Cell, grid_direction
from .hierarchy import descend_pyramid_pdf, descend_pyramid_sample, leaf_density, sample_leaf

#: Fraction of a leaf's width kept clear of its edges when placing a sample
#: (see :func:`place_in_leaf`).
LEAF_EDGE_MARGIN = 2.0**-10


def place_in_leaf(pyramid, leaf: Cell, t: mi.Point2f, prob, valid):
    """(world direction, solid-angle pdf) of the point ``t`` in [0,1)^2 of ``leaf``, chosen with
    probability ``prob``: by the bilinear interpolant of the pyramid's target at the leaf's
    corners (:meth:`EnvPyramid.leaf_corners`); :func:`leaf_pdf` is its density. Lanes that are
    not ``valid`` (no probability, a black map) get pdf 0 and the constant direction +z."""
    valid = valid & (not pyramid.is_black)
    # Keep the point off the leaf's edges: the float32 round trip
    # grid -> world (to_world) -> grid in pdf() moves a direction by
    # ~1e-7, which on an edge can cross into a neighbouring leaf with
    # another (possibly zero) probability. The margin moves at most
    # LEAF_EDGE_MARGIN of a leaf's mass within the leaf; after `depth`
    # rescalings t has only ~2^(depth - 24) resolution anyway.
    t = dr.clip(t, LEAF_EDGE_MARGIN, 1.0 - LEAF_EDGE_MARGIN)
    z, phi, density = sample_leaf("bilinear", leaf, t, pyramid.leaf_corners)
    d = pyramid.world_from_grid(grid_direction(z, phi))
    # A sample of pdf 0 carries no weight: a constant, not a direction drawn for it (a
    # uniform one cost every lane a sine and cosine, 5-8 % of the product warp's time,
    # docs/MEASUREMENTS.md, "The pyramid's depth and the warp's memory").
    d = dr.select(valid, d, mi.Vector3f(0.0, 0.0, 1.0))
    return d, dr.select(valid, prob * density / leaf.area, 0.0)


def leaf_pdf(pyramid, leaf: Cell, z, phi) -> mi.Float:
    """Density (per steradian, given the leaf) with which :func:`place_in_leaf` places a
    point at grid coordinates (z, phi) of ``leaf``."""
    return leaf_density("bilinear", leaf, z, phi, pyramid.leaf_corners) / leaf.area


def finish_sample(pyramid, cell: Cell, t: mi.Point2f, prob, valid):
    """(world direction, solid-angle pdf) of a walk that reached ``cell`` with probability
    ``prob`` and rescaled sample ``t``: the pyramid's descent to its finest level, then
    :func:`place_in_leaf`. :func:`finish_pdf` is its density."""
    leaf, t, p_leaf = descend_pyramid_sample(pyramid, cell, t)
    return place_in_leaf(pyramid, leaf, t, prob * p_leaf, valid)


def finish_pdf(pyramid, cell: Cell, prob, z, phi) -> mi.Float:
    """Density (per steradian) of :func:`finish_sample` at grid coordinates (z, phi) of
    ``cell``, reached with probability ``prob``."""
    leaf, p_leaf = descend_pyramid_pdf(pyramid, cell, z, phi)
    return prob * p_leaf * leaf_pdf(pyramid, leaf, z, phi)
