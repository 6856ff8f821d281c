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
    cosine_only: mi.Bool | bool = False
    """Per lane: the lobe is the clamped cosine about ``normal`` alone (a diffuse
    BSDF): :class:`~.product.ProductWarp` samples it from its cosine tables
    (:mod:`.cosine_table`), without SH levels."""

    def value(self, w: mi.Vector3f) -> mi.Float:
        """The proxy at grid-frame direction ``w``: the same rational glossy lobe as
        :meth:`children_values`, so its integral over the sphere is
        ``diffuse_weight + glossy_weight``."""
        lam = dr.minimum(dr.maximum(self.exponent, 0.0), MAX_SHARPNESS)
        glossy = self.glossy_weight * (1.0 + lam) * (1.0 / (4.0 * math.pi)) \
            / dr.square(1.0 + 0.5 * lam * (1.0 - dr.dot(self.mirror, w)))
        return dr.fma(self.diffuse_weight * (1.0 / math.pi), dr.maximum(dr.dot(self.normal, w), 0.0), glossy)

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


def moment_proxy(coeffs: list) -> ProxyLobe:
    """A one-lobe proxy read off an SH expansion's first two bands, for callers
    of :class:`~.product.ProductWarp` that hold only coefficients.

    The bands 0 and 1 of a function are exact whatever the band limit: they
    are its integral and its first moment, m = integral f(w) w dw. So the
    direction of m and the mean cosine mu = |m| / integral (the lobe's, not its
    band-limited ringing's) come at the price of four coefficients. For the
    real basis of :mod:`mitsuba_shsampling.sh.basis` (y_1^-1 = -K y,
    y_1^0 = K z, y_1^1 = -K x, K = sqrt(3 / 4 pi)),

        m = (4 pi / 3) K (-f_1^1, -f_1^-1, f_1^0),   mu = |(f_1^-1, f_1^0, f_1^1)| / (sqrt(3) f_0^0).

    The exponent is that of the Phong lobe with this mean cosine,
    (s + 1) / (s + 2) = mu, i.e. s = (2 mu - 1) / (1 - mu): a Phong lobe's
    SH expansion gives back its own s, and a function no brighter on one
    side than the other (mu <= 1/2) a uniform proxy (s clamped to 0), below
    which the walk follows the environment. Only the glossy part is used.
    The proxy only steers the walk: the pdf stays exact whatever it is.
    """
    f00, f1m, f10, f1p = coeffs[0], coeffs[1], coeffs[2], coeffs[3]
    axis = mi.Vector3f(-f1p, -f1m, f10)
    length = dr.norm(axis)
    mu = length / (math.sqrt(3.0) * f00)
    # mu >= 1 (a delta, or ringing that outweighs the mean) is the sharpest lobe;
    # mu <= 1/2, no positive mean or a first moment without a direction (zero, NaN,
    # infinite) is none: exponent 0.
    exponent = dr.select(mu < 1.0, dr.fma(2.0, mu, -1.0) / (1.0 - mu), MAX_SHARPNESS)
    has_axis = dr.isfinite(length) & (length > 0.0)
    exponent = dr.select(has_axis & (mu > 0.5), exponent, 0.0)
    mirror = dr.select(has_axis, axis / length, mi.Vector3f(0.0, 0.0, 1.0))
    return ProxyLobe(mirror, mi.Float(0.0), mirror, mi.Float(1.0), exponent)
