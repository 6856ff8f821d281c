"""The lobe proxy in closed form, for the product levels below the SH ones.

:class:`~mitsuba_shsampling.lobes.SceneLobes` describes each shading point's
cosine-weighted BSDF by a two-lobe proxy (grid frame, n the shading normal on
the viewer's side, r the mirror direction, s the fitted Phong exponent):

    q(w) = w_d max(n . w, 0) / pi  +  w_g (s+1)/(2 pi) max(r . w, 0)^s.

Its SH expansion is band-limited (the exponent is widened to what the bands
hold, :attr:`SceneLobes.max_exponent`); a closed form is not, so below the SH
levels it can still steer the product walk towards a sharp lobe.

A walk weights a child cell by the lobe's value at the child's centre times
the environment's exact cell integral. The glossy part is evaluated as the
rational lobe

    g(w) = (1 + lambda) / (4 pi) / (1 + lambda (1 - r . w) / 2)^2,   lambda = s,

which has unit integral over the sphere (exactly), equals cos^s to second
order at the peak (both are 1 - s theta^2 / 2), and falls off like theta^-4,
as a GGX lobe does, instead of vanishing: a cell whose centre misses a lobe
narrower than the cell still gets weight from its flank. It costs a
reciprocal where cos^s would cost a logarithm and an exponential.

The lobe is taken at the cell's centre as it is: blurring it to the cell's
angular size first (adding c x (cell extent)^2 to its variance 1 / s) only
lost, more the more it blurred (docs/MEASUREMENTS.md, "The closed-form
proxy's point value").

Whatever these weights are, the walk's pdf is the exact product of its branch
probabilities (:mod:`.hierarchy`), so they decide how well the samples follow
the integrand, never whether the estimate is right.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import drjit as dr
import mitsuba as mi

from ..grid import Cell

MAX_SHARPNESS = 1e6
"""Cap on lambda: a mirror (s = +inf) stays finite, and float32 still resolves
lambda (1 - r . w) / 2 next to the peak."""


class ProxyLobe(NamedTuple):
    """Per-lane parameters of the two-lobe proxy, in the grid frame."""

    normal: mi.Vector3f
    diffuse_weight: mi.Float
    mirror: mi.Vector3f
    glossy_weight: mi.Float
    exponent: mi.Float
    """The fitted Phong exponent, not widened to the band limit (+inf: mirror)."""

    def children_values(self, cell: Cell, centres) -> tuple:
        """The proxy at the centres of the four children of ``cell`` (order
        (0,0), (0,1), (1,0), (1,1)). ``centres`` = (cos, sin) of the left and
        the right children's phi centres
        (:func:`~mitsuba_shsampling.grid.child_phi_centres`)."""
        quarter_z = 0.5 / 2**cell.level
        lam = dr.minimum(dr.maximum(self.exponent, 0.0), MAX_SHARPNESS)
        glossy = self.glossy_weight * (1.0 + lam) * (1.0 / (4.0 * math.pi))
        # 1 + lambda (1 - r.w) / 2 = (1 + lambda / 2) - (lambda / 2) r.w: one fma per child.
        half_lam = 0.5 * lam
        one_plus_half_lam = 1.0 + half_lam
        diffuse = self.diffuse_weight * (1.0 / math.pi)
        n, r = self.normal, self.mirror
        cos_l, sin_l, cos_r, sin_r = centres
        # A direction is (sin_theta cos_phi, sin_theta sin_phi, z): its dot product with
        # n is sin_theta (n.x cos_phi + n.y sin_phi) + n.z z. The bracket depends on the
        # column only, n.z z on the row only: one fma per child instead of five operations.
        columns = [(dr.fma(n.x, c, n.y * s_), dr.fma(r.x, c, r.y * s_)) for c, s_ in ((cos_l, sin_l), (cos_r, sin_r))]
        values = []
        for z in (cell.zm - quarter_z, cell.zm + quarter_z):
            sin_theta = dr.safe_sqrt(dr.fma(-z, z, 1.0))
            n_z, r_z = n.z * z, r.z * z
            for n_column, r_column in columns:
                cos_n = dr.fma(sin_theta, n_column, n_z)
                cos_m = dr.fma(sin_theta, r_column, r_z)
                falloff = dr.square(dr.fma(-half_lam, cos_m, one_plus_half_lam))
                values.append(dr.fma(diffuse, dr.maximum(cos_n, 0.0), glossy / falloff))
        return tuple(values)
