"""Product sampling: max(SH lobe, 0) x environment luminance.

:class:`ProductWarp` draws world directions with density close to
max(f_SH(omega), 0) * L(omega) / integral, where f_SH is a per-lane SH
expansion in the environment's *grid frame* (docs/ARCHITECTURE.md) and L the
luminance held by an :class:`~mitsuba_shsampling.envmap.pyramid.EnvPyramid`.

Node weights (the four children of the current cell):

* levels ``< sh_depth``: analytic SH cell integral (clamped at 0) times the
  environment cell integral (both exact; their product estimates the integral
  of the product, exactly only at the leaves);
* levels ``>= sh_depth``: the lobe hardly varies across such small cells
  (a band-n lobe varies on the scale of ~pi/n), so the SH factor becomes a
  bilinear interpolation of the lobe's values at the corners of the
  ``sh_depth`` cell (computed once), and only the environment is gathered
  per level. The SH work is then paid for the top levels only while the
  environment's full resolution is still reached.

Whatever the weights, the pdf is the product of the branch probabilities
(see :mod:`.hierarchy`), so sampling is unbiased under MIS.
"""

from __future__ import annotations

import math

import drjit as dr
import mitsuba as mi

from ..sh.basis import bands_of, sh_eval_sum_on_circle
from .hierarchy import check_depth, grid_coordinates, grid_direction, walk_pdf, walk_sample
from .hsw import SHCellWeights, _as_floats


def default_sh_depth(n_bands: int) -> int:
    """Levels with analytic SH weights: cells down to ~1/4 of the lobe's
    finest feature (pi/n), i.e. 2^k >= 4n."""
    return max(2, math.ceil(math.log2(4 * n_bands)))


class ProductWeights:
    """Weight provider for :func:`walk_sample`/:func:`walk_pdf`."""

    def __init__(self, coeffs: list, pyramid, sh_depth: int):
        self.sh = SHCellWeights(coeffs)
        self.pyramid = pyramid
        self.sh_depth = sh_depth

    def root(self):
        return self.sh.root()

    def children(self, state, cell):
        env = self.pyramid.children(cell.level, cell.iz, cell.iphi)
        weights = self._product_weights(state, cell, env)
        if cell.level == 0:
            return weights
        # Product weights are not additive: a child chosen with positive
        # probability can have all four of its own product weights at 0 (lobe
        # clamped where the light is). Fall back to the environment there so
        # no probability is lost; env children of a lit cell are never all 0.
        total = (weights[0] + weights[1]) + (weights[2] + weights[3])
        keep = total > 0
        return tuple(dr.select(keep, w, e) for w, e in zip(weights, env))

    def _product_weights(self, state, cell, env):
        if cell.level < self.sh_depth:
            lobe = self.sh.children(state, cell)
            return tuple(dr.maximum(w, 0.0) * e for w, e in zip(lobe, env))
        if cell.level == self.sh_depth:
            # Corner values of the lobe over this cell, reused by all deeper levels.
            lo = sh_eval_sum_on_circle(self.sh.coeffs, cell.z0, [cell.phi0, cell.phi1])
            hi = sh_eval_sum_on_circle(self.sh.coeffs, cell.z1, [cell.phi0, cell.phi1])
            state["corners"] = [dr.maximum(v, 0.0) for v in lo + hi]
            state["box"] = (cell.z0, cell.z1 - cell.z0, cell.phi0, cell.phi1 - cell.phi0)
        c00, c01, c10, c11 = state["corners"]
        z0, dz, phi0, dphi = state["box"]
        weights = []
        for a, zc in ((0, 0.25), (1, 0.75)):
            tz = (cell.z0 + zc * (cell.z1 - cell.z0) - z0) / dz
            for b, pc in ((0, 0.25), (1, 0.75)):
                tp = (cell.phi0 + pc * (cell.phi1 - cell.phi0) - phi0) / dphi
                lobe = dr.lerp(dr.lerp(c00, c01, tp), dr.lerp(c10, c11, tp), tz)
                weights.append(lobe * env[2 * a + b])
        return tuple(weights)

    def advance(self, state, cell, a, b):
        if cell.level < self.sh_depth - 1:
            return self.sh.advance(state, cell, a, b)
        return state  # below the SH levels only the corner values are carried


class ProductWarp:
    """Product sampler of an SH lobe and an environment map.

    Parameter ``pyramid`` (:class:`EnvPyramid`):
        The environment's luminance pyramid; the leaves are its finest cells,
        inside which directions are uniform.

    Parameter ``sh_depth`` (int or None):
        Levels with analytic SH cell integrals (default: from the band count,
        :func:`default_sh_depth`); deeper levels use a bilinear lobe estimate.

    ``sample(coeffs, u)`` returns (world direction, solid-angle pdf);
    ``pdf(coeffs, d)`` evaluates the density for world directions. ``coeffs``
    are n^2 per-lane SH coefficients in the grid frame. Lanes whose product
    has no positive mass (lobe <= 0 wherever the map is lit, a black map, or
    non-finite coefficients) get pdf 0.
    """

    def __init__(self, pyramid, sh_depth: int | None = None):
        self.pyramid = pyramid
        self.depth = check_depth(pyramid.depth)
        self.sh_depth = sh_depth

    def _provider(self, coeffs):
        coeffs = _as_floats(coeffs)
        sh_depth = default_sh_depth(bands_of(coeffs)) if self.sh_depth is None else self.sh_depth
        return ProductWeights(coeffs, self.pyramid, min(check_depth(sh_depth), self.depth))

    def sample(self, coeffs, u: mi.Point2f):
        """Warp ``u`` in [0,1)^2 to a world direction; returns (direction, pdf)."""
        leaf, t, prob, valid, _ = walk_sample(self._provider(coeffs), self.depth, u)
        valid &= not self.pyramid.is_black
        z = dr.lerp(leaf.z0, leaf.z1, t.x)
        phi = dr.lerp(leaf.phi0, leaf.phi1, t.y)
        d = self.pyramid.world_from_grid(grid_direction(z, phi))
        d = dr.select(valid, d, mi.warp.square_to_uniform_sphere(u))
        return d, dr.select(valid, prob / leaf.area, 0.0)

    def pdf(self, coeffs, d: mi.Vector3f) -> mi.Float:
        """Density (per steradian) with which :meth:`sample` produces world direction ``d``."""
        z, phi = grid_coordinates(self.pyramid.grid_from_world(d))
        leaf, _, prob, _ = walk_pdf(self._provider(coeffs), self.depth, z, phi)
        return prob / leaf.area
