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

Everything here is float64 numpy on the host except the BSDF evaluation, which
is one vectorised ``bsdf.eval`` call per BSDF.
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

    @staticmethod
    def build(axis: np.ndarray, n_theta: int = 96, n_phi: int = 48) -> "LobeQuadrature":
        theta, w_theta, phi = _polar_nodes(n_theta, n_phi)

        e3 = np.asarray(axis, dtype=np.float64) / np.linalg.norm(axis)
        towards_normal = np.array([0.0, 0.0, 1.0]) - e3[2] * e3
        if np.linalg.norm(towards_normal) < 1e-9:
            towards_normal = np.array([1.0, 0.0, 0.0])
        e1 = towards_normal / np.linalg.norm(towards_normal)
        e2 = np.cross(e3, e1)

        tt, pp = np.meshgrid(theta, phi, indexing="ij")
        st = np.sin(tt)
        directions = (np.cos(tt)[..., None] * e3 + (st * np.cos(pp))[..., None] * e1
                      + (st * np.sin(pp))[..., None] * e2)
        weights = np.repeat(w_theta[:, None], n_phi, 1) * (2.0 * math.pi / n_phi)
        cos_to_axis = np.repeat(np.cos(theta)[:, None], n_phi, 1)
        screen = np.zeros((n_theta, n_phi), dtype=bool)
        screen[::SCREEN_STRIDE, ::SCREEN_STRIDE] = True
        return LobeQuadrature(directions.reshape(-1, 3), weights.reshape(-1),
                              cos_to_axis.reshape(-1), screen.reshape(-1))


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
    angles = np.arange(azimuths) * np.pi / azimuths
    uv_count = len(uvs)
    u_count = uv_count * azimuths
    flip = -1.0 if back_side else 1.0

    def turned(d):  # (..., 3) -> (..., azimuths, 3): each direction at every angle, float32
        c, s = np.cos(angles), np.sin(angles)
        x = d[..., None, 0] * c - d[..., None, 1] * s
        y = d[..., None, 0] * s + d[..., None, 1] * c
        z = np.broadcast_to(d[..., None, 2], x.shape)
        return np.stack([x, y, flip * z], axis=-1).reshape(-1, 3).astype(np.float32)

    # The K x M x U table is indexed in the kernel: lane (k, m, a, j) reads view k and
    # light m turned by angle a, at uv position j. Only the small per-view and
    # per-light arrays cross from the host (K M U copies of them cost more than the
    # BSDF evaluations).
    wi = turned(np.stack([view_direction(c) for c in view_cosines]))   # (K azimuths, 3)
    wo = turned(np.asarray(light_directions, dtype=np.float64))        # (K M azimuths, 3)
    lane = dr.arange(mi.UInt32, k_count * m_count * u_count)
    light_index, u = lane // u_count, lane % u_count
    angle, uv_index = u // uv_count, u % uv_count
    view_index = (light_index // m_count) * azimuths + angle

    def gathered(table, index):
        return dr.gather(mi.Vector3f, mi.Vector3f(*(device_array(mi.Float, table[:, i]) for i in range(3))), index)

    si = dr.zeros(mi.SurfaceInteraction3f, k_count * m_count * u_count)
    if mi.is_spectral:
        si.wavelengths = fit_wavelengths()
    si.t = 0.0
    si.n = mi.Normal3f(0.0, 0.0, flip)
    si.sh_frame = mi.Frame3f(mi.Vector3f(1.0, 0.0, 0.0), mi.Vector3f(0.0, 1.0, 0.0),
                             mi.Vector3f(0.0, 0.0, 1.0))
    uvs = np.asarray(uvs, dtype=np.float32)
    si.uv = dr.gather(mi.Point2f, mi.Point2f(device_array(mi.Float, uvs[:, 0]), device_array(mi.Float, uvs[:, 1])), uv_index)
    si.wi = gathered(wi, view_index)
    light = gathered(wo, light_index * azimuths + angle)
    value = luminance(bsdf.eval(mi.BSDFContext(), si, light))
    g = np.array(value, dtype=np.float64).reshape(k_count, m_count, u_count)
    # Negative or non-finite values would make the fit meaningless; they can only
    # come from a broken plugin, and a lobe is non-negative by definition.
    return np.where(np.isfinite(g), np.maximum(g, 0.0), 0.0)


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


def mis_divergence(g: np.ndarray, proxy: np.ndarray, weights: np.ndarray, energy: float):
    """Chi-square divergence of g against the defensive mixture (proxy + g) / 2.

    ``proxy`` has shape (..., M) and integrates (over the sphere) to ``energy``;
    g (M,) must be > 0 on every node (nodes where g = 0 contribute nothing and
    are dropped by the caller) and integrates to ``energy`` over the quadrature.
    Returns an array (...), 0 when the proxy equals g on the hemisphere.
    """
    mixture = 0.5 * (proxy + g)
    return (g * g / mixture) @ weights / energy - 1.0


def fit_two_lobe(g: np.ndarray, quadrature: LobeQuadrature) -> TwoLobeFit:
    """Fit (w_d, w_g, s) of the diffuse + Phong proxy to one tabulated lobe.

    ``g`` (M,) is the lobe on ``quadrature``, whose axis is the Phong axis.

    Coarse grid search over ``PHONG_EXPONENTS`` x ``DIFFUSE_FRACTIONS``, then one
    finer search around the best pair. The coarse grid is screened on a quarter of the
    nodes (:data:`SCREEN_STRIDE`), and its :data:`SHORTLIST` best candidates there are
    weighed again on every node: the coarse pick is the grid's own wherever it is among
    them. (The 560 fits of the built-in scenes and ten rough conductors and plastics are
    the whole grid's bit for bit, in 0.53 s where they took 0.88; docs/MEASUREMENTS.md.)
    Returns all-zero weights when the lobe carries no energy.
    """
    weights = quadrature.weights
    energy = float(g @ weights)
    if not energy > 0.0:
        return TwoLobeFit(0.0, 0.0, 1.0, 0.0)

    # Only nodes where g or a candidate can be large matter; dropping g == 0 nodes
    # is exact for the divergence (the ratio vanishes there).
    keep = g > 0
    nodes = _FitNodes(g, quadrature, keep)
    screen = _FitNodes(g, quadrature, keep & quadrature.screen, weight_scale=SCREEN_STRIDE * SCREEN_STRIDE)

    coarse = screen.divergence(energy, PHONG_EXPONENTS, DIFFUSE_FRACTIONS)
    # The shortlist in the grid's order among equals, so that ties go as the grid's own argmin.
    shortlist = np.argsort(coarse, axis=None, kind="stable")[:SHORTLIST]
    rows, columns = np.unravel_index(shortlist, coarse.shape)
    weighed = nodes.pair_divergence(energy, PHONG_EXPONENTS[rows], DIFFUSE_FRACTIONS[columns])
    best = min(range(len(shortlist)), key=lambda k: (weighed[k], shortlist[k]))
    s, t = PHONG_EXPONENTS[rows[best]], DIFFUSE_FRACTIONS[columns[best]]

    step = PHONG_EXPONENTS[1] / PHONG_EXPONENTS[0]
    fine_s = s * step ** np.linspace(-1.0, 1.0, 7)
    fine_t = np.unique(np.clip(t + np.linspace(-0.1, 0.1, 9), 0.0, 1.0))
    fine = nodes.divergence(energy, fine_s, fine_t)
    i, j = np.unravel_index(np.argmin(fine), fine.shape)
    s, t, d = fine_s[i], fine_t[j], fine[i, j]
    return TwoLobeFit(energy * t, energy * (1.0 - t), float(s), float(d))


SCREEN_STRIDE = 2
"""The coarse search's screen takes every ``SCREEN_STRIDE``-th ring and azimuth of the fitting
quadrature (weights scaled to keep its total)."""

SHORTLIST = 8
"""Coarse candidates the screen passes on to be weighed on every node."""


class _FitNodes:
    """The nodes of a fit where the lobe is positive (``mask``), in float32: the lobe, the
    weights (times ``weight_scale``), the Phong axis cosine and the diffuse lobe."""

    def __init__(self, g: np.ndarray, quadrature: LobeQuadrature, mask: np.ndarray, weight_scale: float = 1.0):
        self.g = g[mask].astype(np.float32)
        self.weights = (quadrature.weights[mask] * weight_scale).astype(np.float32)
        self.cos_r = quadrature.cos_to_axis[mask]
        self.diffuse = (np.maximum(quadrature.directions[mask, 2], 0.0) / math.pi).astype(np.float32)

    def divergence(self, energy: float, exponents: np.ndarray, fractions: np.ndarray) -> np.ndarray:
        """:func:`mis_divergence` of every (exponent, diffuse fraction) pair: (S, T)."""
        glossy = phong_lobe(self.cos_r[None, :], exponents[:, None]).astype(np.float32)  # (S, M)
        d = np.empty((len(exponents), len(fractions)))
        for j, t in enumerate(fractions):
            proxy = np.float32(energy * (1.0 - t)) * glossy + np.float32(energy * t) * self.diffuse
            d[:, j] = mis_divergence(self.g, proxy, self.weights, energy)
        return d

    def pair_divergence(self, energy: float, exponents: np.ndarray, fractions: np.ndarray) -> np.ndarray:
        """:func:`mis_divergence` of each (exponent k, diffuse fraction k) pair: (K,)."""
        glossy = phong_lobe(self.cos_r[None, :], exponents[:, None]).astype(np.float32)  # (K, M)
        proxy = (energy * (1.0 - fractions)).astype(np.float32)[:, None] * glossy \
            + (energy * fractions).astype(np.float32)[:, None] * self.diffuse
        return mis_divergence(self.g, proxy, self.weights, energy)


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
