"""Product sampling: max(SH lobe, 0) x environment luminance, defensively mixed.

:class:`ProductWarp` draws world directions from the mixture
(1 - e) p_product + e p_env (:class:`ProductWeights`), where p_product is close
to max(f_SH(omega), 0) * L(omega) / integral, f_SH a per-lane SH expansion in
the environment's *grid frame* (docs/ARCHITECTURE.md), L the luminance held by
an :class:`~mitsuba_shsampling.envmap.pyramid.EnvPyramid` and p_env that
pyramid's own distribution. The mixture keeps the pdf positive wherever the
map is lit.

Node weights (the four children of the current cell):

* levels ``< sh_depth``: analytic SH cell integral (clamped at 0) times the
  environment cell integral (both exact; their product estimates the integral
  of the product, exactly only at the leaves);
* levels ``sh_depth .. proxy_depth - 1``: the lobe in closed form (the
  per-lane :class:`~.proxy_lobe.ProxyLobe` the integrators fit to the BSDF, at
  its fitted, not band-limited, sharpness; without one the lobe read off the
  coefficients' first two bands, :func:`~.proxy_lobe.moment_proxy`), evaluated
  at the children's centres, times the environment cell integrals;
* deeper levels: the environment cell integrals alone, i.e. the lobe is taken
  as constant inside the chosen cell. The SH work is paid for the top levels
  only while the environment's full resolution is still reached by one gather
  per level.

A bilinear lobe estimate below ``sh_depth`` (from the lobe's values at the
corners of the ``sh_depth`` cell) was measured and not kept: it cost more
kernel operations than one further SH level and gained less
(``docs/MEASUREMENTS.md``, "Product warp below the SH levels"). See
:func:`default_sh_depth` for the choice of the default.

Memory per shading point: the n^2 float32 coefficients (400 B at 10 bands,
1.6 kB at 20), or the n(n+1)/2 + 2(n-1) factors of a rotated zonal lobe, are
the only per-point data; the walk keeps about
n(n+1)/2 + 2n further floats in registers while it runs. The pyramid is
shared by all points (its size: :attr:`EnvPyramid.nbytes`, at most ~39 MB at
its default depth cap).

Whatever the weights, the pdf is the product of the branch probabilities
(see :mod:`.hierarchy`), so sampling is unbiased under MIS. Below the
product levels (``walk_depth`` = max(``sh_depth``, ``proxy_depth``)) those
probabilities telescope to (leaf integral) / (integral of the cell where the
product levels end), which :func:`.hierarchy.descend_pyramid_pdf` evaluates
with two gathers.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import drjit as dr
import mitsuba as mi

from ..grid import Cell, child_phi_centres, grid_coordinates
from ..sh.zonal import RotatedZonalLobes
from .cosine_table import TABLE_DEPTH, CosineTable
from .env_leaves import finish_pdf, finish_sample
from .hierarchy import Split, check_depth, select_child, walk_pdf_absolute, walk_sample_absolute
from .hsw import SHCellState, SHCellWeights, as_lobe, lobe_bands
from .proxy_lobe import ProxyLobe, moment_proxy




def check_sh_depth(sh_depth) -> int:
    """Validate ``sh_depth``: at least 1, so that the root split uses the
    lobe's exact cell integrals. They decide whether the lobe has positive
    mass at all (pdf 0 otherwise); the environment alone could not."""
    check_depth(sh_depth)
    if sh_depth < 1:
        raise ValueError(f"sh_depth must be >= 1, got {sh_depth}")
    return sh_depth


def default_sh_depth(n_bands: int) -> int:
    """Default number of SH levels: the smallest k with 2^k >= 4 n (cells of
    about a quarter of the lobe's finest feature, pi/n), at least 2.

    3 bands: 4, 5: 5, 10: 6, 15: 6, 20: 7. Chosen where kernel operations x
    relative variance of the one-sample product estimate is lowest, or close
    to it (``scripts/bench_product.py --sh-depths``; figures in
    ``docs/MEASUREMENTS.md``, "Product warp below the SH levels").
    """
    return max(2, math.ceil(math.log2(4 * n_bands)))


DEFAULT_PROXY_DEPTH = 6
"""Deepest level whose children are weighted by the closed-form proxy
(:mod:`.proxy_lobe`); chosen with ``sh_depth`` :data:`SH_DEPTH_WITH_PROXY`
(docs/MEASUREMENTS.md, "Band count, SH depth and proxy levels")."""

SH_DEPTH_WITH_PROXY = 2
"""SH levels above closed-form proxy levels: at about the kernel operations of
``sh_depth`` 3 without the proxy, less per-pixel variance on every sphere and
map measured (docs/MEASUREMENTS.md, "Band count, SH depth and proxy levels")."""

DEFAULT_DEFENSIVE_SHARE = 0.1
"""Share of the environment's own distribution in the product strategy (see
:class:`ProductWeights`): it keeps the pdf positive wherever the map is lit,
so a clamped lobe leaves no hole for BSDF samples to find a sun in with MIS
weight 1 (docs/MEASUREMENTS.md, "Defensive share")."""


def check_defensive_share(share) -> float:
    """Validate a defensive share: a float in (0, 1]. 0 is refused because it
    would give up the coverage guarantee (zero-pdf holes where the clamped lobe
    misses light that the BSDF still reflects)."""
    if isinstance(share, bool) or not isinstance(share, (int, float)):
        raise TypeError(f"defensive share must be a float in (0, 1], got {share!r}")
    if not (0.0 < share <= 1.0):
        raise ValueError(f"defensive share must be in (0, 1], got {share}")
    return float(share)


class ProductState(NamedTuple):
    """What :class:`ProductWeights` carries down the tree."""

    sh: SHCellState | None
    """The SH provider's state (None below the SH levels)."""
    product_mass: mi.Float
    """(1 - e) x the product part's probability of the current cell: its share of the mixture W."""
    share: mi.Float | None
    """Per-lane defensive share (e, or 1 where the lobe has no mass); None at the root."""
    centre: tuple | None = None
    """(cos, sin) of the cell's phi centre, on the closed-form proxy levels."""


class ProductSplit(NamedTuple):
    sh: object
    numerators: list
    """The four children's product weights (their environment integrals where the product has no mass)."""
    mass_per_weight: mi.Float
    """The product part's mass per unit of those weights: a child's product mass is the product of the two."""
    share: mi.Float
    centres: tuple | None
    """(cos, sin) of the children's phi centres (closed-form proxy levels)."""


class ProductWeights:
    """Weight provider for :func:`walk_sample_absolute` / :func:`walk_pdf_absolute`:
    a defensive mixture of the product and the environment, in one walk.

    The target is the mixture (Hesterberg 1995)

        q = (1 - e) p_product + e p_env,

    with p_env the pyramid's own distribution and e the defensive share. Both
    are hierarchical over the same cells, so their mixture is too: the weight
    of a child cell c is its absolute mixture probability

        W(c) = (1 - e) P_product(c) + e E(c) / E(root),

    where (1 - e) P_product(c) = (1 - e) P_product(parent) x (product weight of
    c / sum of the four) is carried down the walk and E is the pyramid's cell
    integral. The children's W sum to the parent's, so the walk's branch
    probabilities telescope to W(leaf) (:func:`walk_sample_absolute`), and the
    pdf is exactly q. Hence q >= e p_env: the
    strategy reaches every lit direction whatever the lobe (clamped ringing,
    a proxy that misses part of the BSDF, non-finite coefficients), and its
    estimate is never more than 1/e worse than environment sampling.

    Product weights, levels ``< sh_depth``: max(SH cell integral, 0) x
    environment cell integral; then, down to ``walk_depth``, the closed-form
    proxy at the children's centres x environment cell integral. Below that
    the lobe is taken as constant inside the chosen cell, so both parts of
    the mixture follow the environment there: the children's weights are the
    pyramid's own.

    Lanes whose lobe has no positive mass where the map is lit (or is not
    finite) use e = 1, i.e. plain environment sampling.

    The children's W sum to the parent's up to float32 rounding because the
    pyramid's levels do: maps too dim for that are black to the pyramid
    (:data:`~mitsuba_shsampling.envmap.pyramid.DIM_TOTAL`).
    """

    def __init__(self, coeffs: list, pyramid, sh_depth: int, defensive_share: float,
                 proxy: ProxyLobe | None = None, proxy_depth: int | None = None):
        self.sh = SHCellWeights(coeffs)
        self.pyramid = pyramid
        self.sh_depth = sh_depth
        self.proxy = proxy
        #: Levels [sh_depth, walk_depth) weight the children by the closed-form proxy.
        self.walk_depth = sh_depth if proxy is None or proxy_depth is None else max(sh_depth, proxy_depth)
        self.defensive_share = defensive_share
        self.inv_total = pyramid.inverse_total

    def root(self) -> ProductState:
        # The share is only known once the root's product weights are (children of level 0).
        return ProductState(self.sh.root(), None, None)

    def children(self, state: ProductState, cell: Cell) -> Split:
        env = tuple(self.pyramid.children(cell.level, cell.iz, cell.iphi))
        if cell.level >= self.walk_depth:
            return Split(env, None)
        if cell.level < self.sh_depth:
            lobe = self.sh.children(state.sh, cell)
            sh_pending, lobe_weights, centres = lobe.pending, lobe.weights, lobe.pending.centres
        else:
            centres = child_phi_centres(*state.centre, cell.level)
            sh_pending, lobe_weights = None, self.proxy.children_values(cell, centres)
        product = [dr.select(w > 0, w, 0.0) * e for w, e in zip(lobe_weights, env)]  # NaN -> 0 too
        total = (product[0] + product[1]) + (product[2] + product[3])
        ok = dr.isfinite(total) & (total > 0)
        if cell.level == 0:
            share = dr.select(ok, self.defensive_share, 1.0)
            mass = 1.0 - share
        else:
            share, mass = state.share, state.product_mass
        # Product weights are not additive: a child chosen with positive
        # probability can have all four of its own product weights at 0 (lobe
        # clamped where the light is). Its product part then follows the
        # environment, so no probability is lost.
        env_total = (env[0] + env[1]) + (env[2] + env[3])
        numerators = [dr.select(ok, p, e) for p, e in zip(product, env)]
        # One division per cell, not one per child and part: a division costs
        # about ten multiplications, and the walks ran ~200 of them per lane.
        mass_per_weight = mass / dr.select(ok, total, env_total)
        # Where that is not finite (a dark cell, or sums that underflow) the
        # product part splits evenly: the children's weights must still sum to
        # the parent's, which the walks rely on (walk_sample_absolute).
        even = ~dr.isfinite(mass_per_weight)
        numerators = [dr.select(even, 1.0, n) for n in numerators]
        mass_per_weight = dr.select(even, 0.25 * mass, mass_per_weight)
        env_mass = share * self.inv_total
        weights = tuple(dr.fma(mass_per_weight, n, env_mass * e) for n, e in zip(numerators, env))
        return Split(weights, ProductSplit(sh_pending, numerators, mass_per_weight, share, centres))

    def advance(self, state: ProductState, pending, cell: Cell, a, b) -> ProductState:
        if cell.level >= self.walk_depth:
            return state  # below the product levels nothing is carried
        chosen = select_child(pending.numerators, a, b)
        sh_state = self.sh.advance(state.sh, pending.sh, cell, a, b) if cell.level < self.sh_depth - 1 else None
        centre = None
        if sh_state is None and cell.level + 1 < self.walk_depth:  # the next level is a proxy level
            cos_l, sin_l, cos_r, sin_r = pending.centres
            centre = (dr.select(b, cos_r, cos_l), dr.select(b, sin_r, sin_l))
        return ProductState(sh_state, pending.mass_per_weight * chosen, pending.share, centre)


class ProductWarp:
    """Product sampler of an SH lobe and an environment map.

    Parameter ``pyramid`` (:class:`EnvPyramid`):
        The environment's luminance pyramid; the leaves are its finest cells,
        inside which directions are uniform.

    Parameter ``sh_depth`` (int or None, default :data:`SH_DEPTH_WITH_PROXY`):
        Levels with analytic SH cell integrals, at least 1 (None: from the
        band count, :func:`default_sh_depth`); deeper levels use the
        closed-form proxy down to ``proxy_depth``, then the environment alone.
        Capped at the pyramid's depth.

    Parameter ``defensive_share`` (float in (0, 1]):
        Weight e of the environment's own distribution in the sampled
        mixture (1 - e) product + e environment (:class:`ProductWeights`).

    Parameter ``proxy_depth`` (int or None, default :data:`DEFAULT_PROXY_DEPTH`):
        Levels down to which a closed-form proxy of the lobe weights the
        children below the SH levels (None: none, the environment alone
        below them). Capped at the pyramid's depth.

    Parameter ``cosine_tables`` (bool, default False):
        Build the :class:`~.cosine_table.CosineTable` of the pyramid (10.6 MB,
        where the pyramid is at least :data:`~.cosine_table.TABLE_DEPTH` deep):
        lanes whose proxy is ``cosine_only`` (a diffuse lobe) are then sampled
        from it, at about the cost of the environment's own sampling.

    ``sample(coeffs, u, proxy=None)`` returns (world direction, solid-angle
    pdf); ``pdf(coeffs, d, proxy=None)`` evaluates the density for world
    directions. ``coeffs`` is the lobe in the grid frame: n^2 per-lane SH
    coefficients, or (as the integrators pass it, and cheaper to walk)
    :class:`~mitsuba_shsampling.sh.zonal.RotatedZonalLobes`, zonal lobes about
    per-lane axes in factored form; ``proxy`` the same lobe in closed form (:class:`~.proxy_lobe.ProxyLobe`;
    the integrators fit one per BSDF). Without one, the proxy levels use
    :func:`~.proxy_lobe.moment_proxy`, a lobe read off the coefficients'
    first two bands, so the SH cell integrals (about 0.8k kernel operations
    a level at 10 bands) are paid on the top levels only.
    The pdf is positive wherever the pyramid is (every lit direction), for any
    coefficients; only a black map gives pdf 0.
    """

    def __init__(self, pyramid, sh_depth: int | None = SH_DEPTH_WITH_PROXY,
                 defensive_share: float = DEFAULT_DEFENSIVE_SHARE,
                 proxy_depth: int | None = DEFAULT_PROXY_DEPTH, cosine_tables: bool = False):
        self.pyramid = pyramid
        self.depth = check_depth(pyramid.depth)
        #: Levels with analytic SH weights (None: chosen from the band count).
        self.sh_depth = None if sh_depth is None else check_sh_depth(sh_depth)
        self.defensive_share = check_defensive_share(defensive_share)
        self.proxy_depth = None if proxy_depth is None else min(check_depth(proxy_depth), self.depth)
        #: The diffuse lobes' sampler (None: every lane walks its SH lobe).
        self.cosine_table = (CosineTable(pyramid, self.defensive_share)
                             if cosine_tables and self.depth >= TABLE_DEPTH else None)

    def weights(self, coeffs, proxy: ProxyLobe | None = None) -> ProductWeights:
        """The weight provider that :meth:`sample` and :meth:`pdf` walk (the cost
        benchmark, ``scripts/bench_cost_breakdown.py``, walks its levels apart)."""
        coeffs = as_lobe(coeffs)
        sh_depth = min(self.sh_depth_for(lobe_bands(coeffs)), self.depth)
        if proxy is None and self.proxy_depth is not None and self.proxy_depth > sh_depth:
            proxy = moment_proxy(coeffs.coefficients(2) if isinstance(coeffs, RotatedZonalLobes) else coeffs)
        return ProductWeights(coeffs, self.pyramid, sh_depth, self.defensive_share, proxy, self.proxy_depth)

    def sh_depth_for(self, n_bands: int) -> int:
        """The SH levels the walk runs for lobes of ``n_bands`` bands."""
        return default_sh_depth(n_bands) if self.sh_depth is None else self.sh_depth

    def _by_lobe(self, table_method: str, lobe_fn, coeffs, x, proxy: ProxyLobe | None):
        """The cosine table's ``table_method`` (``sample`` or ``pdf``) of (normal, x) in the lanes
        of a diffuse lobe (``proxy.cosine_only``), ``lobe_fn(coeffs, x, proxy)`` in the others: a
        symbolic branch, so a SIMD packet runs only the walks its lanes need, and none is traced
        where ``cosine_only`` is a constant."""
        if self.cosine_table is None or proxy is None or proxy.cosine_only is False:
            return lobe_fn(coeffs, x, proxy)
        table_fn = getattr(self.cosine_table, table_method)
        if proxy.cosine_only is True:  # every lane's lobe is a cosine: no SH code at all
            return table_fn(proxy.normal, x)
        return dr.if_stmt(args=(coeffs, x, proxy), cond=mi.Bool(proxy.cosine_only),
                          true_fn=lambda c, v, p: table_fn(p.normal, v), false_fn=lobe_fn)

    def sample(self, coeffs, u: mi.Point2f, proxy: ProxyLobe | None = None):
        """Warp ``u`` in [0,1)^2 to a world direction; returns (direction, pdf)."""
        return self._by_lobe("sample", self._sample_lobe, coeffs, u, proxy)

    def pdf(self, coeffs, d: mi.Vector3f, proxy: ProxyLobe | None = None) -> mi.Float:
        """Density (per steradian) with which :meth:`sample` produces world direction ``d``."""
        return self._by_lobe("pdf", self._lobe_pdf, coeffs, d, proxy)

    def _sample_lobe(self, coeffs, u: mi.Point2f, proxy: ProxyLobe | None = None):
        """:meth:`sample` by the SH and proxy levels."""
        provider = self.weights(coeffs, proxy)
        cell, t, prob, valid, _ = walk_sample_absolute(provider, provider.walk_depth, u)
        # Below the product levels both parts of the mixture follow the
        # environment: its own pyramid finishes the walk.
        return finish_sample(self.pyramid, cell, t, prob, valid)

    def _lobe_pdf(self, coeffs, d: mi.Vector3f, proxy: ProxyLobe | None = None) -> mi.Float:
        """Density of :meth:`_sample_lobe`."""
        z, phi = grid_coordinates(self.pyramid.grid_from_world(d))
        provider = self.weights(coeffs, proxy)
        cell, prob, _ = walk_pdf_absolute(provider, provider.walk_depth, z, phi)
        return finish_pdf(self.pyramid, cell, prob, z, phi)
