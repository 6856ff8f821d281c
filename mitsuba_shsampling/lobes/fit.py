"""Fit a two-lobe zonal proxy to a BSDF's own ``eval`` (host side, once per BSDF).

The quantity approximated is the cosine-weighted lobe seen from a fixed view
direction, as a function of the light direction. In Mitsuba's naming (``si.wi``
points to the viewer, ``wo`` to the light) that is

    g(wo) = luminance(bsdf.eval(ctx, si, wo))      (eval already holds |cos theta_o|)

and the proxy, in the local shading frame (normal n = +z), is

    q(wo) = w_d * max(cos(n, wo), 0) / pi  +  w_g * (s+1)/(2 pi) * max(cos(r, wo), 0)^s

with r the mirror direction of ``si.wi`` about n. Both lobes integrate to one, so
w_d + w_g is the lobe's energy (the directional albedo for this view direction).

Parameters are fitted per view elevation ``cos theta_i = si.wi.z`` on a few nodes,
by a grid search that minimises the chi-square divergence of g against the
defensive mixture (q + g) / 2, i.e. the relative variance of one balance-heuristic
MIS sample drawn from the proxy or from a perfect BSDF sampler under constant
lighting. The mixture keeps the criterion finite where the proxy has no support
(a Phong lobe misses some of a rough lobe's tail) while still penalising a proxy
that is much too narrow or too wide. The energy w_d + w_g is matched exactly
(on the fitting quadrature).

The BSDF is evaluated in one kernel per BSDF and side (every view node, light node and
surface position), and the search runs in one kernel a stage over every view node
(:func:`fit_two_lobes`); the quadratures and the Phong lobe's table are made once per
process in float64 numpy.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import drjit as dr
import mitsuba as mi
import numpy as np

from ..device_arrays import device_array

PHONG_EXPONENTS = np.geomspace(0.5, 4000.0, 32)
"""Candidate Phong exponents of the coarse search (log-spaced)."""

DIFFUSE_FRACTIONS = np.array([0.0, 0.02, 0.05, 0.1, 0.2, 0.3, 0.4, 0.5, 0.6, 0.7, 0.85, 1.0])
"""Candidate values of w_d / (w_d + w_g) of the coarse search."""


N_THETA, N_PHI = 96, 48
"""Rings and azimuths of a fitting quadrature (:class:`LobeQuadrature`)."""


@dataclass
class LobeQuadrature:
    """Quadrature over the sphere in polar coordinates about a lobe axis.

    Directions are in the local shading frame (z = normal). The polar angle
    about ``axis`` is theta' = pi tau^2 with Gauss-Legendre nodes in tau, which
    packs nodes around the axis (the first ring sits at ~1e-6 rad for 96
    nodes): a Phong or microfacet lobe of any width used here is resolved, and
    every Phong candidate depends on ``cos_to_axis`` only. The azimuth about the
    axis uses the midpoint rule on [0, pi] with phi' = 0 towards the normal:
    the view direction, the normal and the mirror axis share the x-z plane, and
    isotropic lobes are symmetric about it, so each node also stands for its
    mirror image (the weights carry the factor 2).

    Fields (numpy float64): ``directions`` (M, 3), ``weights`` (M,) in
    steradians summing to 4 pi, ``cos_to_axis`` (M,); ``screen`` (M,) bool.
    """
    directions: np.ndarray
    weights: np.ndarray
    cos_to_axis: np.ndarray
    screen: np.ndarray | None = None
    """(M,) bool: the nodes of the coarse search's screen (every :data:`SCREEN_STRIDE`-th
    ring and azimuth)."""
    axis: np.ndarray | None = None
    """(3,) the unit axis."""

    @staticmethod
    def build(axis: np.ndarray, n_theta: int = N_THETA, n_phi: int = N_PHI) -> "LobeQuadrature":
        theta, w_theta, phi = _polar_nodes(n_theta, n_phi)
        e1, e2, e3 = _axis_frame(axis)
        tt, pp = np.meshgrid(theta, phi, indexing="ij")
        st = np.sin(tt)
        directions = (np.cos(tt)[..., None] * e3 + (st * np.cos(pp))[..., None] * e1
                      + (st * np.sin(pp))[..., None] * e2)
        weights = np.repeat(w_theta[:, None], n_phi, 1) * (2.0 * math.pi / n_phi)
        cos_to_axis = np.repeat(np.cos(theta)[:, None], n_phi, 1)
        screen = np.zeros((n_theta, n_phi), dtype=bool)
        screen[::SCREEN_STRIDE, ::SCREEN_STRIDE] = True
        return LobeQuadrature(directions.reshape(-1, 3), weights.reshape(-1),
                              cos_to_axis.reshape(-1), screen.reshape(-1), e3)


def _axis_frame(axis: np.ndarray) -> tuple:
    """(e1, e2, e3) of a quadrature about ``axis``: e3 the unit axis, e1 towards the normal
    (phi' = 0), e2 = e3 x e1."""
    e3 = np.asarray(axis, dtype=np.float64) / np.linalg.norm(axis)
    towards_normal = np.array([0.0, 0.0, 1.0]) - e3[2] * e3
    if np.linalg.norm(towards_normal) < 1e-9:
        towards_normal = np.array([1.0, 0.0, 0.0])
    e1 = towards_normal / np.linalg.norm(towards_normal)
    return e1, np.cross(e3, e1), e3


@functools.lru_cache(maxsize=None)
def _polar_nodes(n_theta: int, n_phi: int):
    """The axis-independent part of :meth:`LobeQuadrature.build`: Gauss-Legendre nodes
    in tau = sqrt(theta / pi) (dense near the axis, where lobes peak), their solid-angle
    weights per unit phi, and the phi nodes. A scene's fits build hundreds of
    quadratures; the nodes are computed once (``leggauss`` was a third of their cost)."""
    x, w = np.polynomial.legendre.leggauss(n_theta)
    tau, w_tau = 0.5 * (x + 1.0), 0.5 * w
    theta = math.pi * tau * tau
    w_theta = 2.0 * math.pi * tau * w_tau * np.sin(theta)
    phi = (np.arange(n_phi) + 0.5) * (math.pi / n_phi)
    for array in (theta, w_theta, phi):
        array.setflags(write=False)  # shared by every quadrature
    return theta, w_theta, phi


def view_direction(cos_theta: float) -> np.ndarray:
    """Local view direction (``si.wi``) in the x-z plane with the given cos theta."""
    return np.array([math.sqrt(max(1.0 - cos_theta * cos_theta, 0.0)), 0.0, cos_theta])


def mirror_direction(wi: np.ndarray) -> np.ndarray:
    """Mirror direction of a local direction about the normal (+z)."""
    return np.array([-wi[0], -wi[1], wi[2]])


def fit_wavelengths():
    """In spectral variants, the wavelengths at which a lobe is tabulated: one fixed,
    stratified set drawn as Mitsuba's sensors draw theirs (``sample_rgb_spectrum``), so
    that the lobe's scalar weight (:func:`luminance`: their mean) spans the visible range
    and is the same in every process."""
    wavelengths, _ = mi.sample_rgb_spectrum(mi.sample_shifted(mi.Float(0.125)))
    return wavelengths


def luminance(value) -> mi.Float:
    """Scalar weight of a BSDF value: luminance in RGB variants, the value otherwise."""
    if mi.is_rgb:
        return mi.luminance(value)
    if mi.is_monochromatic:
        return value[0]
    return dr.mean(value)


def tabulate_lobe(bsdf: mi.BSDF, view_cosines: np.ndarray, light_directions: np.ndarray,
                  uvs: np.ndarray, back_side: bool = False, azimuths: int = 1) -> np.ndarray:
    """Cosine-weighted lobe g of ``bsdf`` at given light directions, per view elevation.

    Parameter ``view_cosines`` (K,): cos theta of ``si.wi`` (> 0; ``si.wi`` lies
    in the x-z plane, x >= 0).
    Parameter ``light_directions`` (K, M, 3): local light directions per view.
    Parameter ``uvs`` (U, 2): surface uv positions.
    Parameter ``back_side``: evaluate the lobe below the surface instead (view
    and light directions mirrored to z < 0); the result is expressed in the
    mirrored frame (z -> -z), so the same fit applies.
    Parameter ``azimuths``: for an anisotropic BSDF, the view and light directions
    are also turned together about the normal by ``azimuths`` angles in [0, pi);
    each counts as one more surface position, so a mean over positions is the
    lobe averaged over the view's azimuth (an isotropic proxy).

    Returns an array (K, M, U * azimuths) of g values (luminance, per steradian).
    """
    k_count, m_count = light_directions.shape[:2]
    directions = _turned_directions(view_cosines, np.asarray(light_directions, dtype=np.float64), back_side, azimuths)
    values = _lobe_values(bsdf, directions, uvs, back_side)
    return np.array(values, dtype=np.float64).reshape(k_count, m_count, len(uvs) * azimuths)


def mean_mirror_lobe(bsdf: mi.BSDF, view_cosines: np.ndarray, uvs: np.ndarray, back_side: bool = False,
                     azimuths: int = 1) -> mi.Float:
    """:func:`tabulate_lobe` on the :func:`mirror_quadrature` of each view elevation, averaged
    over the surface positions (and azimuths) on the device: K M float32 values, view-major,
    ready for :func:`fit_two_lobes`. The directions are made once per process."""
    directions = _mirror_directions(tuple(float(c) for c in view_cosines), back_side, azimuths)
    values = mi.Float64(_lobe_values(bsdf, directions, uvs, back_side))
    positions = len(uvs) * azimuths
    return mi.Float(dr.block_sum(values, positions, mode="evaluated") / positions) if positions > 1 \
        else mi.Float(values)


@functools.lru_cache(maxsize=8)
def _mirror_directions(view_cosines: tuple, back_side: bool, azimuths: int) -> tuple:
    """:func:`_turned_directions` of the mirror quadratures' nodes, turned in a kernel."""
    nodes = mirror_nodes(view_cosines)
    angles = np.arange(azimuths) * np.pi / azimuths
    lane = dr.arange(mi.UInt32, dr.width(nodes) * azimuths)
    node, angle = lane // azimuths, lane % azimuths
    c = dr.gather(mi.Float64, device_array(mi.Float64, np.cos(angles)), angle)
    s = dr.gather(mi.Float64, device_array(mi.Float64, np.sin(angles)), angle)
    d = dr.gather(mi.Vector3d, nodes, node)
    wo = mi.Vector3f(d.x * c - d.y * s, d.x * s + d.y * c, -d.z if back_side else d.z)
    wi = _turned_directions(np.array(view_cosines), np.zeros((len(view_cosines), 1, 3)), back_side, azimuths)[0]
    dr.eval(wo)
    return wi, wo, len(view_cosines), N_THETA * N_PHI, azimuths


@functools.lru_cache(maxsize=8)
def mirror_nodes(view_cosines: tuple) -> mi.Vector3d:
    """The nodes' directions of :func:`mirror_quadrature` for each view cosine, K M float64
    values view-major, in one kernel (in numpy, with their turns, they were a tenth of a new
    scene's lobe fits)."""
    theta, _, phi = _polar_nodes(N_THETA, N_PHI)
    frames = np.stack([np.stack(_axis_frame(mirror_direction(view_direction(c)))) for c in view_cosines])  # (K, 3, 3)
    u32, f64 = mi.UInt32, mi.Float64
    lane = dr.arange(u32, len(view_cosines) * N_THETA * N_PHI)
    view, node = lane // (N_THETA * N_PHI), lane % (N_THETA * N_PHI)
    ring, azimuth = node // N_PHI, node % N_PHI

    def at(values, index):
        return dr.gather(f64, device_array(f64, values), index)

    cos_t, sin_t = at(np.cos(theta), ring), at(np.sin(theta), ring)
    cos_p, sin_p = at(np.cos(phi), azimuth), at(np.sin(phi), azimuth)
    e = [mi.Vector3d(*(at(frames[:, i, a], view) for a in range(3))) for i in range(3)]
    nodes = cos_t * e[2] + (sin_t * cos_p) * e[0] + (sin_t * sin_p) * e[1]
    dr.eval(nodes)
    return nodes


def _turned_directions(view_cosines: np.ndarray, light_directions: np.ndarray, back_side: bool,
                       azimuths: int) -> tuple:
    """The view directions (K azimuths) and light directions (K M azimuths) of :func:`tabulate_lobe`
    on the device, each turned by every azimuth, mirrored below the surface for ``back_side``."""
    k_count, m_count = light_directions.shape[:2]
    angles = np.arange(azimuths) * np.pi / azimuths
    flip = -1.0 if back_side else 1.0

    def turned(d):  # (..., 3) -> (..., azimuths, 3): each direction at every angle, float32
        c, s = np.cos(angles), np.sin(angles)
        x = d[..., None, 0] * c - d[..., None, 1] * s
        y = d[..., None, 0] * s + d[..., None, 1] * c
        z = np.broadcast_to(d[..., None, 2], x.shape)
        return np.stack([x, y, flip * z], axis=-1).reshape(-1, 3).astype(np.float32)

    def on_device(table):
        return mi.Vector3f(*(device_array(mi.Float, table[:, i]) for i in range(3)))

    wi = turned(np.stack([view_direction(c) for c in view_cosines]))   # (K azimuths, 3)
    wo = turned(light_directions)                                       # (K M azimuths, 3)
    return on_device(wi), on_device(wo), k_count, m_count, azimuths


def _lobe_values(bsdf: mi.BSDF, directions: tuple, uvs: np.ndarray, back_side: bool) -> mi.Float:
    """luminance(bsdf.eval) at every (view k, light m, azimuth a, uv position j), in that
    order (j fastest), on the device; non-finite and negative values as 0."""
    wi, wo, k_count, m_count, azimuths = directions
    uv_count = len(uvs)
    u_count = uv_count * azimuths
    # The K x M x U table is indexed in the kernel: lane (k, m, a, j) reads view k and
    # light m turned by angle a, at uv position j. Only the small per-view and
    # per-light arrays cross from the host (K M U copies of them cost more than the
    # BSDF evaluations).
    lane = dr.arange(mi.UInt32, k_count * m_count * u_count)
    light_index, u = lane // u_count, lane % u_count
    angle, uv_index = u // uv_count, u % uv_count
    view_index = (light_index // m_count) * azimuths + angle

    si = dr.zeros(mi.SurfaceInteraction3f, k_count * m_count * u_count)
    if mi.is_spectral:
        si.wavelengths = fit_wavelengths()
    si.t = 0.0
    si.n = mi.Normal3f(0.0, 0.0, -1.0 if back_side else 1.0)
    si.sh_frame = mi.Frame3f(mi.Vector3f(1.0, 0.0, 0.0), mi.Vector3f(0.0, 1.0, 0.0),
                             mi.Vector3f(0.0, 0.0, 1.0))
    uvs = np.asarray(uvs, dtype=np.float32)
    si.uv = dr.gather(mi.Point2f, mi.Point2f(device_array(mi.Float, uvs[:, 0]), device_array(mi.Float, uvs[:, 1])), uv_index)
    si.wi = dr.gather(mi.Vector3f, wi, view_index)
    light = dr.gather(mi.Vector3f, wo, light_index * azimuths + angle)
    value = luminance(bsdf.eval(mi.BSDFContext(), si, light))
    # Negative or non-finite values would make the fit meaningless; they can only
    # come from a broken plugin, and a lobe is non-negative by definition.
    return dr.select(dr.isfinite(value), dr.maximum(value, 0.0), 0.0)


@functools.lru_cache(maxsize=256)
def mirror_quadrature(view_cosine: float) -> LobeQuadrature:
    """The fitting quadrature of one view elevation: centred on the mirror direction.
    The same for every BSDF, so built once per elevation (its arrays are read-only)."""
    quadrature = LobeQuadrature.build(mirror_direction(view_direction(view_cosine)))
    for array in (quadrature.directions, quadrature.weights, quadrature.cos_to_axis, quadrature.screen):
        array.flags.writeable = False
    return quadrature


def phong_lobe(cos_to_axis: np.ndarray, s) -> np.ndarray:
    """Normalised Phong lobe (s+1)/(2 pi) max(cos, 0)^s (unit integral over the sphere).

    ``s`` may be an array (broadcast against ``cos_to_axis``).
    """
    c = np.maximum(cos_to_axis, 0.0)
    with np.errstate(divide="ignore"):
        log_c = np.where(c > 0, np.log(np.maximum(c, 1e-300)), -np.inf)
    return (s + 1.0) / (2.0 * math.pi) * np.exp(s * log_c)


@dataclass
class TwoLobeFit:
    """Fitted proxy parameters for one view elevation.

    ``diffuse_weight`` w_d and ``glossy_weight`` w_g (luminance; their sum is
    the lobe's energy), ``exponent`` s of the Phong lobe about the mirror
    direction, ``divergence``: the criterion at the optimum (0 = perfect).
    """
    diffuse_weight: float
    glossy_weight: float
    exponent: float
    divergence: float


def fit_two_lobe(g: np.ndarray, quadrature: LobeQuadrature) -> TwoLobeFit:
    """Fit (w_d, w_g, s) of the diffuse + Phong proxy to one tabulated lobe: :func:`fit_two_lobes`
    for one lobe ``g`` (M,) on ``quadrature`` (a :func:`mirror_quadrature`)."""
    return fit_two_lobes(np.asarray(g, dtype=np.float64)[None, :], (float(quadrature.axis[2]),), np.array([0]))[0]


def fit_two_lobes(g, view_cosines: tuple, views: np.ndarray) -> list[TwoLobeFit]:
    """Fit (w_d, w_g, s) of the diffuse + Phong proxy to F tabulated lobes at once.

    ``g``: the lobes, (F, M) numpy or F M values on the device, lobe f on the nodes of
    ``mirror_quadrature(view_cosines[views[f]])`` (their axis is the Phong axis).

    Coarse grid search over ``PHONG_EXPONENTS`` x ``DIFFUSE_FRACTIONS``, then one finer
    search around the best pair. The coarse grid is screened on a quarter of the nodes
    (:data:`SCREEN_STRIDE`), and its :data:`SHORTLIST` best candidates there are weighed again
    on every node: the coarse pick is the grid's own wherever it is among them. Each stage is
    one kernel over every lobe and candidate (:func:`_divergences`); the Phong lobe's values
    at the nodes come from a table made once per process (:func:`_phong_table`): the same
    float32 terms as the numpy search this replaces, summed in float64. (The numpy search
    took 0.2-0.3 s of a new scene's set-up for its 176 fits; docs/MEASUREMENTS.md.)
    Returns all-zero weights for a lobe that carries no energy.
    """
    tables = _FitTables.of(tuple(float(c) for c in view_cosines))
    count = len(views)
    g = device_array(mi.Float, g) if isinstance(g, np.ndarray) else mi.Float(g)
    views = np.asarray(views, dtype=np.uint32)
    energy = dr.block_sum(mi.Float64(g) * dr.gather(mi.Float64, tables.weights64, dr.arange(mi.UInt32, dr.width(g))
                                                     % tables.nodes), tables.nodes, mode="evaluated")
    energy = np.asarray(energy.numpy(), dtype=np.float64)
    lobes = _Lobes(g, energy, views, tables)

    # Coarse, on the screen: every exponent (as lanes) against every diffuse fraction.
    exponents = np.arange(len(PHONG_EXPONENTS))
    coarse = lobes.divergences(np.repeat(exponents[None, :], count, 0) * FINE_STEPS + FINE_STEPS // 2,
                               np.broadcast_to(DIFFUSE_FRACTIONS, (count, len(exponents), len(DIFFUSE_FRACTIONS))),
                               screen=True)                                       # (F, S, T)
    flat = coarse.reshape(count, -1)
    # The shortlist in the grid's order among equals, so that ties go as the grid's own argmin.
    shortlist = np.argsort(flat, axis=1, kind="stable")[:, :SHORTLIST]            # (F, K)
    rows, columns = np.unravel_index(shortlist, coarse.shape[1:])
    weighed = lobes.divergences(rows * FINE_STEPS + FINE_STEPS // 2, DIFFUSE_FRACTIONS[columns][..., None])[..., 0]
    best = np.array([min(range(SHORTLIST), key=lambda k: (weighed[f, k], shortlist[f, k])) for f in range(count)])
    row, column = rows[np.arange(count), best], columns[np.arange(count), best]

    # Fine: the exponents a step either side of the pick (as lanes), fractions 0.1 either side.
    fine_t = np.clip(DIFFUSE_FRACTIONS[column][:, None] + np.linspace(-0.1, 0.1, 9)[None, :], 0.0, 1.0)
    fine = lobes.divergences(row[:, None] * FINE_STEPS + np.arange(FINE_STEPS)[None, :],
                             np.repeat(fine_t[:, None, :], FINE_STEPS, 1))           # (F, 7, 9)
    fits = []
    for f in range(count):
        if not energy[f] > 0.0:
            fits.append(TwoLobeFit(0.0, 0.0, 1.0, 0.0))
            continue
        # The first minimum in row-major order: clipped fractions repeat at the ends with
        # equal divergences, so this is the pick among the distinct fractions too.
        i, j = np.unravel_index(np.argmin(fine[f]), fine[f].shape)
        t, e = fine_t[f, j], energy[f]
        fits.append(TwoLobeFit(e * t, e * (1.0 - t), float(FINE_EXPONENTS[row[f], i]), float(fine[f, i, j])))
    return fits


SCREEN_STRIDE = 2
"""The coarse search's screen takes every ``SCREEN_STRIDE``-th ring and azimuth of the fitting
quadrature (weights scaled to keep its total)."""

SHORTLIST = 8
"""Coarse candidates the screen passes on to be weighed on every node."""

FINE_STEPS = 7
"""Exponents of the fine search: the coarse pick and three either side, up to one coarse step."""

FINE_EXPONENTS = PHONG_EXPONENTS[:, None] * (PHONG_EXPONENTS[1] / PHONG_EXPONENTS[0]) \
    ** np.linspace(-1.0, 1.0, FINE_STEPS)[None, :]
"""(coarse exponent, fine step) -> exponent; the middle step is the coarse exponent itself."""

CHUNK_NODES = 128
"""Nodes one lane of :meth:`_Lobes.divergences` sums (the rest of a lobe's nodes in other lanes)."""


class _FitTables:
    """What every fit on the same view elevations shares, on the device: the nodes' weights
    (float32, and float64 for the energy), the diffuse lobe per view (max(z, 0) / pi), the
    Phong lobe of every :data:`FINE_EXPONENTS` value at every node (float32, computed in
    float64) and the screen's node indices. Made once per set of view elevations."""

    _made: dict = {}
    MADE_ENTRIES = 8

    def __init__(self, view_cosines: tuple):
        _, w_theta, _ = _polar_nodes(N_THETA, N_PHI)
        weights = np.repeat(w_theta[:, None], N_PHI, 1).reshape(-1) * (2.0 * math.pi / N_PHI)  # as a quadrature's
        self.nodes = len(weights)
        self.weights64 = device_array(mi.Float64, weights)
        self.weights = device_array(mi.Float, weights)
        self.diffuse = mi.Float(dr.maximum(mirror_nodes(view_cosines).z, 0.0) / math.pi)
        dr.eval(self.diffuse)
        self.phong = _phong_table()
        screen = np.zeros((N_THETA, N_PHI), dtype=bool)
        screen[::SCREEN_STRIDE, ::SCREEN_STRIDE] = True
        screen = np.flatnonzero(screen).astype(np.uint32)
        self.screen = device_array(mi.UInt32, screen)
        self.screen_nodes = len(screen)

    @classmethod
    def of(cls, view_cosines: tuple) -> "_FitTables":
        tables = cls._made.get(view_cosines)
        if tables is None:
            if len(cls._made) >= cls.MADE_ENTRIES:
                cls._made.pop(next(iter(cls._made)))
            tables = cls._made[view_cosines] = cls(view_cosines)
        return tables


@functools.lru_cache(maxsize=None)
def _phong_table() -> mi.Float:
    """The normalised Phong lobe of each :data:`FINE_EXPONENTS` value (rows, in its flat order)
    at each node of the fitting quadrature (columns): float64 math, stored as float32, as the
    numpy search computed it. The nodes' angle to the axis is the same for every elevation."""
    theta, _, _ = _polar_nodes(N_THETA, N_PHI)
    cos_to_axis = np.repeat(np.cos(theta)[:, None], N_PHI, 1).reshape(-1)  # as a quadrature's
    return device_array(mi.Float, phong_lobe(cos_to_axis[None, :], FINE_EXPONENTS.reshape(-1, 1)))


class _Lobes:
    """F tabulated lobes (float32 on the device, M nodes each), their energies and views."""

    def __init__(self, g: mi.Float, energy: np.ndarray, views: np.ndarray, tables: _FitTables):
        self.g, self.energy, self.views, self.tables = g, energy, views, tables

    def divergences(self, exponents: np.ndarray, fractions: np.ndarray, screen: bool = False) -> np.ndarray:
        """The chi-square divergence of lobe f against the defensive mixture (proxy + g) / 2,
        ``sum_m w_m g_m^2 / ((proxy_m + g_m) / 2) / energy - 1`` (0 when the proxy equals g on the
        hemisphere), for the proxy of exponent ``exponents[f, s]``
        (a flat :data:`FINE_EXPONENTS` index) and diffuse fraction ``fractions[f, s, t]``, on
        the nodes where the lobe is positive (of the screen only, weights scaled, with
        ``screen``): (F, S, T). One kernel, a lane per (lobe, exponent, run of
        :data:`CHUNK_NODES` nodes) summing every fraction's terms; the runs' sums added in float64."""
        t = self.tables
        count, s_count = exponents.shape
        t_count = fractions.shape[2]
        nodes = t.screen_nodes if screen else t.nodes
        chunks = -(-nodes // CHUNK_NODES)
        u32, f32 = mi.UInt32, mi.Float
        lane = dr.arange(u32, count * s_count * chunks)
        candidate, chunk = lane // dr.opaque(u32, chunks), lane % dr.opaque(u32, chunks)
        fit = candidate // dr.opaque(u32, s_count)
        row = dr.gather(u32, device_array(u32, exponents), candidate)
        view = dr.gather(u32, device_array(u32, self.views), fit)
        energy = np.repeat(self.energy, s_count)[:, None]
        # The proxy's two weights per fraction, rounded to float32 as the numpy search did.
        glossy_weight = device_array(f32, (energy * (1.0 - fractions.reshape(-1, t_count))).astype(np.float32))
        diffuse_weight = device_array(f32, (energy * fractions.reshape(-1, t_count)).astype(np.float32))
        a = [dr.gather(f32, glossy_weight, candidate * t_count + k) for k in range(t_count)]
        b = [dr.gather(f32, diffuse_weight, candidate * t_count + k) for k in range(t_count)]
        scale = float(SCREEN_STRIDE * SCREEN_STRIDE) if screen else 1.0
        size, m_count = dr.opaque(u32, nodes), dr.opaque(u32, t.nodes)
        end = dr.minimum((chunk + 1) * CHUNK_NODES, size)

        def body(j, sums):
            node = dr.gather(u32, t.screen, j) if screen else j
            g = dr.gather(f32, self.g, fit * m_count + node)
            weight = dr.gather(f32, t.weights, node) * scale
            diffuse = dr.gather(f32, t.diffuse, view * m_count + node)
            phong = dr.gather(f32, t.phong, row * m_count + node)
            lit = g > 0
            terms = [dr.select(lit, g * g / (0.5 * (a[k] * phong + b[k] * diffuse + g)) * weight, 0.0)
                     for k in range(t_count)]
            return j + 1, [s + mi.Float64(x) for s, x in zip(sums, terms)]

        _, sums = dr.while_loop((chunk * CHUNK_NODES, [dr.zeros(mi.Float64, dr.width(lane)) for _ in range(t_count)]),
                                lambda j, sums: j < end, body)
        dr.eval(sums)  # one kernel for every fraction's sums (else one each)
        totals = [dr.block_sum(x, chunks, mode="evaluated") for x in sums]
        dr.eval(totals)
        out = np.stack([np.asarray(x.numpy(), dtype=np.float64) for x in totals], axis=-1)
        with np.errstate(divide="ignore", invalid="ignore"):
            return out.reshape(count, s_count, t_count) / energy.reshape(count, s_count, 1) - 1.0


def uv_positions(count: int) -> np.ndarray:
    """``count`` well-spread uv positions in [0,1)^2 (2D Halton points, bases 2 and 3)."""
    def radical_inverse(i, base):
        f, r = 1.0, 0.0
        while i > 0:
            f /= base
            r += f * (i % base)
            i //= base
        return r
    return np.array([[radical_inverse(i + 1, 2), radical_inverse(i + 1, 3)]
                     for i in range(count)])


def varies_over_surface(bsdf: mi.BSDF, uvs: np.ndarray) -> bool:
    """True if ``bsdf.eval`` changes with the uv position (textured parameters).

    Probes a few view/light pairs at every uv position: cheaper than fitting the
    mean lobe over many positions when the BSDF is uniform. (Mitsuba does not set
    ``BSDFFlags.SpatiallyVarying`` for textured parameters, so it cannot be used.)
    """
    views = np.array([0.3, 0.9])
    lights = np.stack([mirror_quadrature(c).directions[::397] for c in views])
    g = tabulate_lobe(bsdf, views, lights, uvs)
    return not np.allclose(g, g[:, :, :1], rtol=1e-5, atol=1e-7)
