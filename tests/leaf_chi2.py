"""A chi-square test for densities that are bilinear inside each bin and jump between bins.

The product warp's density is bilinear in (cos theta, phi) inside each leaf of
the pyramid and discontinuous across leaves (each leaf has its own
normalisation); with a 1e5 sun the jump is five orders of magnitude.
``mitsuba.chi2.ChiSquareTest`` integrates the pdf over a bin by the trapezoid
rule: exact for a bilinear density only if the bin lies inside one leaf, and
its outermost nodes sit 1e-4 node spacings inside the bin, about 1e-7 in
cos theta, the size of the float32 round trip grid -> world -> grid that the
pdf takes (a node at a sun leaf's edge can read the dark neighbour's density).

:class:`LeafAlignedChiSquareTest` integrates each bin with Gauss-Legendre nodes
instead: exact for a bilinear density, and no node closer to a bin edge than
7 % of its width. With bins aligned to the leaves the expected counts are then
exact up to float32 evaluation.
"""

from __future__ import annotations

import time

import drjit as dr
import mitsuba as mi
import numpy as np
from mitsuba import chi2

GAUSS_NODES = 4
"""Gauss-Legendre nodes per bin and dimension (exact for polynomials of degree 7)."""


class LeafAlignedChiSquareTest(chi2.ChiSquareTest):
    """``ChiSquareTest`` whose expected counts come from Gauss-Legendre
    quadrature inside each bin (``ires`` is ignored)."""

    def tabulate_pdf(self):
        # Mitsuba's run() reports this method's time under the histogram's names.
        self.histogram_start = time.time()
        nodes, weights = np.polynomial.legendre.leggauss(GAUSS_NODES)
        nodes, weights = 0.5 * (nodes + 1.0), 0.5 * weights  # on [0, 1]
        per_bin = GAUSS_NODES**2
        cell_count = self.res.x * self.res.y
        index = dr.arange(mi.UInt32, cell_count * per_bin)
        cell_index, node_index = index // per_bin, index % per_bin
        cell = mi.Vector2u(cell_index % self.res.x, cell_index // self.res.x)
        node_x, node_y = node_index % GAUSS_NODES, node_index // GAUSS_NODES
        offset = mi.Vector2f(dr.gather(mi.Float, mi.Float(nodes), node_x),
                             dr.gather(mi.Float, mi.Float(nodes), node_y))
        weight = dr.gather(mi.Float, mi.Float(weights), node_x) * dr.gather(mi.Float, mi.Float(weights), node_y)
        cell_size = self.bounds.extents() / self.res
        p = self.bounds.min + (mi.Vector2f(cell) + offset) * cell_size
        pdf = self.pdf_func(self.domain.map_forward(p))
        self.pdf = dr.block_sum(pdf * weight * (dr.prod(cell_size) * self.sample_count), per_bin)
        self.pdf_sum = dr.sum(self.pdf) / self.sample_count
        if not dr.min(self.pdf)[0] >= 0:
            self._log("Failure: Encountered a cell with a negative PDF value")
            self.fail = True
        if self.pdf_sum[0] > 1.1:
            self._log(f"Failure: PDF integrates to a value greater than 1.0: {self.pdf_sum[0]}")
            self.fail = True
        self.histogram_end = time.time()
