"""The equal-area grid every sampler and the environment pyramid share.

Convention, stated once: a unit direction d of a z-up frame (the *grid
frame*) has cylinder coordinates

    z = d.z in [-1, 1],    phi = atan2(d.y, d.x) in [0, 2 pi),

and d(omega) = dz dphi, so a cell [z0, z1] x [phi0, phi1] has solid angle
(z1 - z0)(phi1 - phi0) and a density uniform in (z, phi) is uniform in solid
angle: no Jacobian anywhere. Level k of the grid splits both ranges into 2^k
equal parts; cell (iz, iphi) of level k is row iz (z ascending) and column
iphi (phi ascending), and its children at level k + 1 are (2 iz + a,
2 iphi + b) with a, b in {0, 1}: a picks the upper z half, b the upper phi
half. The grid frame of an environment map is defined by
:class:`~mitsuba_shsampling.envmap.pyramid.EnvPyramid`; SH functions are
expanded in the same frame.
"""

from __future__ import annotations

import math

import drjit as dr
import mitsuba as mi

TWO_PI = 2.0 * math.pi


class Cell:
    """Bounds of the current cell of every lane at one level.

    ``iz`` and ``iphi`` may be per-lane ``mi.UInt32`` or Python ints; the bounds
    are ``mi.Float`` (z0, z1, zm: lower, upper, middle z; likewise phi); the
    extents ``dz``, ``dphi`` and the solid angle ``area`` are Python floats,
    equal for all cells of a level, unless given: a cell of a level that the
    kernel reads from a device value (an environment pyramid's finest level,
    :meth:`~mitsuba_shsampling.envmap.pyramid.EnvPyramid.leaf_cell`) takes its
    extents from there, so that no kernel holds the level as a literal.
    """

    def __init__(self, level, iz, iphi, dz=None, dphi=None):
        self.level, self.iz, self.iphi = level, iz, iphi
        if dz is None:
            dz, dphi = 2.0 / 2**level, TWO_PI / 2**level
        self.dz, self.dphi = dz, dphi
        self.z0 = dr.fma(mi.Float(iz), dz, -1.0)
        self.z1 = self.z0 + dz
        self.zm = self.z0 + 0.5 * dz
        self.phi0 = mi.Float(iphi) * dphi
        self.phi1 = self.phi0 + dphi
        self.phim = self.phi0 + 0.5 * dphi
        self.area = dz * dphi


def child_phi_centres(cos_c, sin_c, level: int):
    """(cos, sin) of the phi centres of the left and the right children of a
    level-``level`` cell whose phi centre has cosine ``cos_c`` and sine
    ``sin_c``: c -+ h, h = pi / 2^(level + 1), by angle addition (h is a
    Python constant, so no sine or cosine is evaluated per lane).

    Returns (cos_left, sin_left, cos_right, sin_right)."""
    h = math.pi / 2 ** (level + 1)
    cos_h, sin_h = math.cos(h), math.sin(h)
    return (dr.fma(cos_c, cos_h, sin_c * sin_h), dr.fma(sin_c, cos_h, -cos_c * sin_h),
            dr.fma(cos_c, cos_h, -sin_c * sin_h), dr.fma(sin_c, cos_h, cos_c * sin_h))


def grid_direction(z, phi) -> mi.Vector3f:
    """Unit direction (grid frame) of cylinder coordinates (z, phi)."""
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


def cell_index(level: int | mi.UInt32, z: mi.Float, phi: mi.Float) -> tuple[mi.UInt32, mi.UInt32]:
    """Cell (iz, iphi) of ``level`` holding grid coordinates (z, phi), by
    rounding down; points on the domain boundary are clamped into the edge
    cells. (The walks find cells by comparisons with the midpoints instead,
    which agrees except within a float rounding of a cell edge.)"""
    cells = mi.Float(mi.UInt32(1) << mi.UInt32(level))
    iz = mi.UInt32(dr.clip((z + 1) * 0.5 * cells, 0, cells - 1))
    iphi = mi.UInt32(dr.clip(phi * (1 / TWO_PI) * cells, 0, cells - 1))
    return iz, iphi


def interval(level: int, index, x0: float, x1: float):
    """(lower bound, midpoint, upper bound) of cell ``index`` at ``level`` of
    the binary split of [x0, x1] (the 1D grid of the strip warps)."""
    width = (x1 - x0) / 2**level
    lo = dr.fma(mi.Float(index), width, x0)
    return lo, lo + 0.5 * width, lo + width
