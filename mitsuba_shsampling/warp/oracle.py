"""The oracle: exact tabulated product sampling, the ideal the SH product is measured against.

:class:`OracleWarp` samples, per lane, the product of a non-negative function
f (a BSDF value at one shading point, in the integrators) and an environment,
tabulated on the N x N cells of level k = log2 N of the environment's pyramid:

    w(c) = f(omega_c) E(c),

omega_c the direction of the cell's centre and E(c) the pyramid's exact
luminance integral over the cell (a sun smaller than a cell is never missed).
Like :class:`~mitsuba_shsampling.warp.product.ProductWarp` it draws from a
defensive mixture,

    P(c) = (1 - e) w(c) / W + e E(c) / E(root),    W = sum_c w(c),

and inside the chosen cell it follows the environment down to the pyramid's
leaves (:func:`~.hierarchy.descend_pyramid_sample`), uniform in the leaf. So

    pdf(omega) = P(c) * E(leaf) / E(c) / leaf_area >= e p_env(omega):

positive wherever the map is lit, whatever f (coverage). Lanes where W is 0 or
not finite use e = 1 (the environment's own distribution).

Cost. Nothing is stored per lane but W: :meth:`OracleWarp.tabulate` evaluates
f at all N^2 cell centres once per shading point (a symbolic loop), and each
:meth:`OracleWarp.sample` of the product part walks the cells again, row sums
first (stopping at the chosen row, N^2 / 2 evaluations on average), then the
N cells of that row. :meth:`OracleWarp.pdf` evaluates f once, at the centre of
the direction's cell. That is what makes it an oracle (a reference, thousands
of BSDF evaluations per sample) and not a sampler to render with.

Exactness. The second walk adds the same weights in the same order as the
first, so its running sums reach W exactly; the row and column searches
compare against u W and u (row sum), and fall back to the last cell of
positive weight should rounding ever leave the sample beyond the end. The
pdf is the closed form above, evaluated alike by ``sample`` and ``pdf``.
"""

from __future__ import annotations

from typing import Callable, NamedTuple

import drjit as dr
import mitsuba as mi

from ..grid import Cell, grid_coordinates, grid_direction
from .env_leaves import finish_pdf, finish_sample
from .hierarchy import LAST_BELOW_ONE, descend_pyramid_sample
from .product import DEFAULT_DEFENSIVE_SHARE, check_defensive_share

#: Cells per side of the table. Measured (64 px, 8 spp, 8 passes, MSE against ``direct``):
#: on a GGX 0.1 sphere under immenstadter_horn, oracle-only sampling gave 0.175 / 0.131 /
#: 0.081 / 0.078 at N = 16 / 32 / 64 / 128, at 8 / 24 / 89 / 222x the time of ``direct``;
#: a diffuse sphere under studio_small_03 was flat from N = 16 (0.096 / 0.091 / 0.088).
#: N = 64 is where the glossy case stops improving: the table then resolves the lobe.
DEFAULT_RESOLUTION = 64
#: Largest table (65536 cells: over 10^5 BSDF evaluations per sample).
MAX_RESOLUTION = 256

Lobe = Callable[[mi.Vector3f, mi.Bool], mi.Float]
"""f(world direction, active): the non-negative per-lane factor of the product
(negative and NaN values count as 0)."""


def check_resolution(resolution) -> int:
    """Validate a table resolution: a power of two in [2, :data:`MAX_RESOLUTION`]."""
    if isinstance(resolution, bool) or not isinstance(resolution, int):
        raise TypeError(f"oracle resolution must be an int, got {resolution!r}")
    if not (2 <= resolution <= MAX_RESOLUTION and resolution & (resolution - 1) == 0):
        raise ValueError(f"oracle resolution must be a power of two in [2, {MAX_RESOLUTION}], got {resolution}")
    return resolution


class OracleTable(NamedTuple):
    """What :meth:`OracleWarp.tabulate` keeps per lane for ``sample`` and ``pdf``."""

    total: mi.Float
    """W, the sum of the cell weights (1 where unusable, see ``share``)."""
    share: mi.Float
    """Defensive share of the lane: e, or 1 where W is 0 or not finite."""


class OracleWarp:
    """Exact tabulated product of a per-lane function and an environment pyramid.

    Parameter ``pyramid`` (:class:`~mitsuba_shsampling.envmap.pyramid.EnvPyramid`):
        The environment's luminance pyramid (the map itself, not MIS-compensated:
        the defensive part must cover every lit direction).

    Parameter ``resolution`` (int):
        Cells per side N of the table, a power of two; capped at the pyramid's
        finest level (``level`` is log2 of what is used).

    Parameter ``defensive_share`` (float in (0, 1]):
        Weight e of the environment's own distribution in the mixture.

    ``tabulate(f, active)`` returns the :class:`OracleTable` of a lane;
    ``sample(f, table, u, active)`` returns (world direction, solid-angle pdf);
    ``pdf(f, table, d, active)`` the density of world direction ``d``.
    """

    def __init__(self, pyramid, resolution: int = DEFAULT_RESOLUTION,
                 defensive_share: float = DEFAULT_DEFENSIVE_SHARE):
        self.pyramid = pyramid
        self.level = min(check_resolution(resolution).bit_length() - 1, pyramid.depth)
        self.resolution = 1 << self.level
        self.defensive_share = check_defensive_share(defensive_share)
        self.inv_total = pyramid.inverse_total

    # ------------------------------------------------------------ the table

    def cell_weight(self, f: Lobe, iz: mi.UInt32, iphi: mi.UInt32, active: mi.Bool) -> mi.Float:
        """w(c) = max(f(centre of c), 0) E(c) for cell (iz, iphi) of :attr:`level`."""
        cell = Cell(self.level, iz, iphi)
        energy = self.pyramid.cell_integral(self.level, iz, iphi, active)
        # Dark cells skip f: it is a BSDF evaluation in the integrators.
        centre = self.pyramid.world_from_grid(grid_direction(cell.zm, cell.phim))
        value = f(centre, active & (energy > 0))
        return dr.select(value > 0, value, 0.0) * energy  # NaN -> 0 too

    @dr.syntax
    def tabulate(self, f: Lobe, active: mi.Bool = True) -> OracleTable:
        """W of each lane: one pass over the N^2 cells (row sums, then their sum,
        the order in which :meth:`sample` adds them again)."""
        n, level = self.resolution, self.level
        active = mi.Bool(active)
        i = mi.UInt32(0)
        total, row = mi.Float(0.0), mi.Float(0.0)
        while active & (i < n * n):
            row += self.cell_weight(f, i >> level, i & (n - 1), active)
            if (i & (n - 1)) == n - 1:
                total += row
                row = mi.Float(0.0)
            i += 1
        ok = active & dr.isfinite(total) & (total > 0)
        return OracleTable(dr.select(ok, total, 1.0), dr.select(ok, self.defensive_share, 1.0))

    def cell_probability(self, f: Lobe, table: OracleTable, cell: Cell, active: mi.Bool) -> mi.Float:
        """P(c) of a cell of :attr:`level`: (1 - e) w(c) / W + e E(c) / E(root)."""
        energy = self.pyramid.cell_integral(self.level, cell.iz, cell.iphi, active)
        product = dr.select(table.share < 1.0,
                            (1.0 - table.share) * self.cell_weight(f, cell.iz, cell.iphi, active) / table.total,
                            0.0)
        return product + table.share * self.inv_total * energy

    # ------------------------------------------------------ sampling and pdf

    def sample(self, f: Lobe, table: OracleTable, u: mi.Point2f, active: mi.Bool = True):
        """Warp ``u`` in [0,1)^2 to a world direction; returns (direction, pdf)."""
        active = mi.Bool(active) & (not self.pyramid.is_black)
        u = mi.Point2f(dr.clip(u.x, 0.0, LAST_BELOW_ONE), dr.clip(u.y, 0.0, LAST_BELOW_ONE))
        # Mixture component first: u.x < e picks the environment.
        from_env = u.x < table.share
        ux = dr.select(from_env, u.x / table.share, (u.x - table.share) / (1.0 - table.share))
        u = mi.Point2f(dr.clip(ux, 0.0, LAST_BELOW_ONE), u.y)
        env_cell, env_t, _ = descend_pyramid_sample(
            self.pyramid, Cell(0, mi.UInt32(0), mi.UInt32(0)), u, self.level)
        iz, iphi, t = self._pick_cell(f, table, u, active & ~from_env)
        cell = Cell(self.level, dr.select(from_env, env_cell.iz, iz), dr.select(from_env, env_cell.iphi, iphi))
        t = dr.select(from_env, env_t, t)
        # Inside the cell both components follow the environment.
        return finish_sample(self.pyramid, cell, t, self.cell_probability(f, table, cell, active), mi.Bool(active))

    def pdf(self, f: Lobe, table: OracleTable, d: mi.Vector3f, active: mi.Bool = True) -> mi.Float:
        """Density (per steradian) with which :meth:`sample` produces world direction ``d``;
        one evaluation of ``f``."""
        z, phi = grid_coordinates(self.pyramid.grid_from_world(d))
        # The cell is found by midpoint comparisons, as descend_pyramid_pdf finds the leaf.
        iz, iphi = mi.UInt32(0), mi.UInt32(0)
        for level in range(self.level):
            step = Cell(level, iz, iphi)
            iz = 2 * iz + dr.select(z >= step.zm, 1, 0)
            iphi = 2 * iphi + dr.select(phi >= step.phim, 1, 0)
        cell = Cell(self.level, iz, iphi)
        active = mi.Bool(active) & (not self.pyramid.is_black)
        return dr.select(active, finish_pdf(self.pyramid, cell, self.cell_probability(f, table, cell, active), z, phi),
                         0.0)

    @dr.syntax
    def _pick_cell(self, f: Lobe, table: OracleTable, u: mi.Point2f, active: mi.Bool):
        """Cell (iz, iphi) with probability w(c) / W and ``u`` rescaled into it:
        the row by u.x among the row sums, then the column by u.y within the row."""
        n, level = self.resolution, self.level
        # Row search: running row sums until they pass u.x W.
        target = u.x * table.total
        i = mi.UInt32(0)
        before, row = mi.Float(0.0), mi.Float(0.0)
        row_iz, row_before, row_sum = mi.UInt32(0), mi.Float(0.0), mi.Float(0.0)
        searching = mi.Bool(active)
        while searching & (i < n * n):
            row += self.cell_weight(f, i >> level, i & (n - 1), searching)
            if (i & (n - 1)) == n - 1:
                if row > 0:
                    # The last row of positive weight so far: the choice, or the
                    # fallback should rounding leave the target beyond the end.
                    row_iz, row_before, row_sum = i >> level, before, row
                    searching = before + row < target
                before += row
                row = mi.Float(0.0)
            i += 1

        # Column search within the row, against u.y times the same row sum.
        target_phi = u.y * row_sum
        j = mi.UInt32(0)
        before = mi.Float(0.0)
        col, col_before, col_weight = mi.UInt32(0), mi.Float(0.0), mi.Float(1.0)
        searching = mi.Bool(active)
        while searching & (j < n):
            w = self.cell_weight(f, row_iz, j, searching)
            if w > 0:
                col, col_before, col_weight = j, before, w
                searching = before + w < target_phi
            before += w
            j += 1

        t = mi.Point2f((target - row_before) / dr.select(row_sum > 0, row_sum, 1.0),
                       (target_phi - col_before) / col_weight)
        t = mi.Point2f(dr.clip(t.x, 0.0, LAST_BELOW_ONE), dr.clip(t.y, 0.0, LAST_BELOW_ONE))
        return row_iz, col, t

