"""Per-shading-point SH lobes of every BSDF in a scene (:class:`SceneLobes`).

Host side, once per scene: each shape's BSDF is classified (product lobe, delta,
unsupported), its two-lobe proxy (``lobes.fit``) is fitted on a few view
elevations, and the parameters go into one flat table. Per lane, inside a traced
integrator ``sample()``: the BSDF's registry id selects its table row, the view
elevation interpolates the parameters, and two zonal lobes are turned to the
grid frame. One kernel, no host round trip.

The proxy, per lane, in the grid frame (n = shading normal on the viewer's side,
r = mirror direction of ``si.wi`` about the shading normal):

    q(w) = w_d * max(cos(n, w), 0) / pi  +  w_g * (s+1)/(2 pi) * max(cos(r, w), 0)^s

band-limited: the diffuse part keeps 3 bands (l <= 2, 99 % of the clamped
cosine's energy), the Phong part ``n_bands``. The proxy is *not* zeroed below
the surface's horizon (a Phong lobe about a grazing r spills below it, and the
band limit rings): the product sampler clamps negative values, and MIS with BSDF
sampling (whose pdf is exactly zero there) keeps the estimator unbiased, so the
wasted samples only cost variance.
"""

from __future__ import annotations

import warnings
from typing import Callable

import drjit as dr
import mitsuba as mi
import numpy as np

from ..build_cache import cached_build, content_key
from ..device_arrays import device_array
from ..scene_materials import registry_id
from ..sh.basis import MAX_ORDER
from ..sh.zonal import RotatedZonalLobes, clamped_cosine_attenuation, phong_attenuation, rotate_zonal_lobes
from ..warp.proxy_lobe import ProxyLobe
from .fit import fit_two_lobes, mean_mirror_lobe, uv_positions, varies_over_surface
from ..traversal import content_parts
from .perturbed_frames import FRAME_WRAPPERS, PerturbedNormal, nested_bsdf

BAND_ATTENUATION_TOL = 0.1
"""A lobe "needs" n bands when every attenuation |lambda_l|, l >= n, is below this
(truncation then rings by a few % of the peak; Phong s = 20 needs 10 bands)."""

DIFFUSE_BANDS = 3
"""Bands kept for the diffuse (clamped cosine) part, and for diffuse-only scenes."""

MAX_BANDS = MAX_ORDER + 1
"""The SH basis goes to l = MAX_ORDER."""

# 8 bands: 10-20 bands cost more time than they saved variance end to end
# (docs/MEASUREMENTS.md, "Band count, SH depth and proxy levels").
DEFAULT_MAX_BANDS = 8
"""Cap on a scene's band count unless the caller sets one (the plugins' ``max_bands``)."""

MIN_GLOSSY_FRACTION = 0.05
"""A fitted Phong lobe carrying less than this fraction of the energy does not
raise the scene's band count (it is a minor correction to a diffuse lobe)."""

MIN_VIEW_COSINE = 0.02
"""Grazing limit of the fitted view elevations; lanes below reuse this node."""


def check_max_bands(max_bands: int) -> None:
    """Raise ValueError unless ``max_bands`` is an int in [DIFFUSE_BANDS, MAX_BANDS]."""
    if isinstance(max_bands, bool) or not isinstance(max_bands, int) \
            or not DIFFUSE_BANDS <= max_bands <= MAX_BANDS:
        raise ValueError(f"max_bands must be an int in [{DIFFUSE_BANDS}, {MAX_BANDS}], got {max_bands!r}")


def bands_for_exponent(s: float, tol: float = BAND_ATTENUATION_TOL, limit: int = 64) -> int:
    """Bands a normalised Phong lobe of exponent ``s`` needs: the smallest n with
    |lambda_l(s)| <= tol for all n <= l < ``limit``."""
    lam = phong_attenuation(float(s), limit)
    n = limit
    while n > 1 and abs(lam[n - 1]) <= tol:
        n -= 1
    return n


def max_exponent_for_bands(n_bands: int, tol: float = BAND_ATTENUATION_TOL) -> float:
    """Largest Phong exponent that ``n_bands`` bands represent (inverse of
    :func:`bands_for_exponent`, by bisection in log s)."""
    lo, hi = 0.0, 1e6
    if bands_for_exponent(hi, tol) <= n_bands:
        return hi
    for _ in range(60):
        mid = 0.5 * (lo + hi)
        if bands_for_exponent(mid, tol) <= n_bands:
            lo = mid
        else:
            hi = mid
    return lo


ANISOTROPIC_AZIMUTHS = 8
"""View azimuths an anisotropic lobe is averaged over: its proxy is the isotropic
lobe of the same energy and mean sharpness (the product then follows it loosely,
BSDF sampling under MIS takes the rest, and the chooser decides whether it pays)."""

def is_cosine_lobe(bsdf: mi.BSDF) -> bool:
    """The cosine-weighted lobe of ``bsdf`` is a clamped cosine (times an albedo) for
    every view: it reflects diffusely and has no glossy part (by its flags; a
    frame-perturbing wrapper by its nested BSDF's, about the perturbed normal).
    Such a lobe's product with the environment depends on the normal alone
    (:mod:`~mitsuba_shsampling.warp.cosine_table`)."""
    if bsdf.class_name() in FRAME_WRAPPERS:
        nested = nested_bsdf(bsdf)
        return nested is not None and is_cosine_lobe(nested)
    flags = int(bsdf.flags())
    return (mi.has_flag(flags, mi.BSDFFlags.DiffuseReflection) and not flags & int(mi.BSDFFlags.Glossy)
            and not mi.has_flag(flags, mi.BSDFFlags.DiffuseTransmission))


def lobe_support(bsdf: mi.BSDF) -> str:
    """How product sampling treats ``bsdf``, decided from its flags.

    - ``"delta"``: only Dirac (or null) components, nothing to sample from an SH lobe;
    - ``"unsupported"``: with a non-Dirac transmission component (the proxy is a
      reflection model);
    - ``"product"``: everything else; the proxy is fitted to its ``eval``
      (averaged over the view's azimuth for anisotropic lobes).

    A wrapper that perturbs the shading frame (:data:`FRAME_WRAPPERS`) is treated
    as its nested BSDF: that BSDF's lobe is fitted, and oriented per lane about the
    perturbed normal (:mod:`.perturbed_frames`).
    """
    if bsdf.class_name() in FRAME_WRAPPERS:
        nested = nested_bsdf(bsdf)
        # One perturbation per lane is modelled: a wrapper of a wrapper has no lobe.
        if nested is None or nested.class_name() in FRAME_WRAPPERS:
            return "unsupported"
        return lobe_support(nested)
    flags = int(bsdf.flags())
    smooth = int(mi.BSDFFlags.Diffuse) | int(mi.BSDFFlags.Glossy)
    if not flags & smooth:
        return "delta"
    if mi.has_flag(flags, mi.BSDFFlags.DiffuseTransmission) or mi.has_flag(flags, mi.BSDFFlags.GlossyTransmission):
        return "unsupported"
    return "product"


class SceneLobes:
    r"""SH proxies of the cosine-weighted BSDF lobes of every shape in a scene.

    Parameters:

    - ``scene`` (mi.Scene): the BSDFs of ``scene.shapes()`` are fitted once, here.
    - ``max_bands`` (int, default :data:`DEFAULT_MAX_BANDS`): cap on the scene's band count.
    - ``view_nodes`` (int, default 16): view elevations fitted per BSDF and side,
      uniform in cos theta on [0.02, 1]; parameters are interpolated linearly in
      between (the exponent in log space).
    - ``uv_samples`` (int, default 16): textured BSDFs are represented by their
      mean lobe over this many uv positions (Halton points); the representative
      roughness is therefore the one of the uv-averaged lobe, not of any texel.

    Attributes: ``n_bands`` (int, 0 when no BSDF needs product sampling),
    ``has_product_lobes`` (bool), ``fits`` (dict: BSDF id string -> fitted
    parameters, for reports), ``max_exponent`` (float: per-lane Phong exponents
    are clamped to what ``n_bands`` represents, so a near-specular lobe becomes a
    wider, ringing-free one rather than a ringing one).
    """

    def __init__(self, scene: mi.Scene, max_bands: int = DEFAULT_MAX_BANDS, view_nodes: int = 16,
                 uv_samples: int = 16):
        check_max_bands(max_bands)
        if view_nodes < 2:
            raise ValueError(f"view_nodes must be >= 2, got {view_nodes}")
        self.max_bands = max_bands
        self.view_nodes = view_nodes
        self.view_cosines = np.linspace(MIN_VIEW_COSINE, 1.0, view_nodes)
        self.fits: dict[str, np.ndarray] = {}

        uvs = uv_positions(uv_samples)
        # Row 0 stays all-zero: lanes of delta, unsupported or missing BSDFs read it.
        rows = [np.zeros((2, view_nodes, 3))]
        row_of_id: dict[int, int] = {}
        needed_bands = 0
        #: Some smooth BSDF has no product lobe (anisotropic, transmissive, a
        #: frame-perturbing wrapper, or an unusable fit): its lanes sample the
        #: environment alone.
        self.has_unsupported_lobes = False
        #: Registry id -> BSDF, for the BSDFs with a product lobe (one table row each).
        self.bsdfs_with_lobes: dict[int, mi.BSDF] = {}
        #: Registry id -> (that id as an opaque value, the perturbed normal) of a frame-perturbing
        #: wrapper with a lobe. Opaque, not a literal, for the reason of
        #: :func:`~mitsuba_shsampling.integrators.environment.emitter_id`.
        self._perturbed: dict[int, tuple[mi.UInt32, PerturbedNormal]] = {}
        #: Registry ids of the BSDFs whose lobe is a clamped cosine (:func:`is_cosine_lobe`).
        self.cosine_ids: set[int] = set()
        for shape in scene.shapes():
            bsdf = shape.bsdf()
            if bsdf is None:
                continue
            key = registry_id(bsdf)
            if key in row_of_id:
                continue
            support, params = self._classify_and_fit(shape, bsdf, uvs)
            if support == "unsupported":
                self.has_unsupported_lobes = True
            if support != "product":
                row_of_id[key] = 0
                continue
            self.fits[bsdf.id()] = params
            self.bsdfs_with_lobes[key] = bsdf
            if bsdf.class_name() in FRAME_WRAPPERS:
                self._perturbed[key] = (dr.opaque(mi.UInt32, key), PerturbedNormal(bsdf))
            row_of_id[key] = len(rows)
            rows.append(params)
            if is_cosine_lobe(bsdf):
                self.cosine_ids.add(key)
            needed_bands = max(needed_bands, self._bands_needed(params))

        self.has_product_lobes = len(rows) > 1
        self.n_bands = min(needed_bands, max_bands) if self.has_product_lobes else 0
        self.max_exponent = max_exponent_for_bands(self.n_bands) if self.n_bands else 0.0

        table = np.stack(rows)
        # The exponent is stored as log(s) (interpolated in log space); unused
        # entries (zero energy) get log 1 = 0.
        table[..., 2] = np.log(np.maximum(table[..., 2], 1e-6))
        self._table = device_array(mi.Float, table)
        id_table = np.zeros(max(row_of_id, default=0) + 1, dtype=np.uint32)
        for key, row in row_of_id.items():
            id_table[key] = row
        self._row_of_id = device_array(mi.UInt32, id_table)
        #: Some BSDF's lobe is a clamped cosine (:func:`is_cosine_lobe`).
        self.has_cosine_lobes = bool(self.cosine_ids)
        self._rows = dict(row_of_id)
        self.sample_from_tables(self.cosine_ids)
        # Opaque: the largest registry id changes with the order in which Mitsuba's parallel
        # loading creates the objects, and a literal would make the kernel new in such a process.
        self._row_of_id_size = dr.opaque(mi.UInt32, len(id_table))

    def _classify_and_fit(self, shape: mi.Shape, bsdf: mi.BSDF, uvs: np.ndarray) -> tuple[str, np.ndarray | None]:
        """``(support, params)`` of a shape's BSDF: :func:`lobe_support`, turned
        ``"unsupported"`` where the fit is unusable, and the fitted parameters where it has a
        product lobe; a warning says why a BSDF gets none (not for an emitter's own shape)."""
        support = lobe_support(bsdf)
        wrapper = bsdf.class_name() in FRAME_WRAPPERS
        # A wrapper's lobe is its nested BSDF's, about the perturbed normal.
        params = self._fit_bsdf(nested_bsdf(bsdf) if wrapper else bsdf, uvs) if support == "product" else None
        why = None
        if support == "unsupported":
            why = ("its nested BSDF is transmissive, itself a wrapper of the shading frame, or not found"
                   if wrapper else "it is transmissive")
        elif support == "product" and not self._fit_is_usable(params):
            support = "unsupported"
            # An emitter's own shape gets a black BSDF by default: nothing
            # to warn about (its lanes still sample the environment alone).
            why = None if shape.is_emitter() else "its fitted lobe has no energy at some view elevation"
        if why is not None:
            warnings.warn(
                f"SceneLobes: BSDF '{bsdf.id()}' ({bsdf.class_name()}, flags "
                f"{int(bsdf.flags()):#x}): {why}; it has no product lobe, and its surfaces use "
                "Mitsuba's envmap sampling (the environment strategies).", stacklevel=3)
        return support, params

    def sample_from_tables(self, keys) -> None:
        """The cosine lobes (registry ids among :attr:`cosine_ids`) whose lanes are marked
        ``cosine_only`` (sampled from the product's cosine tables); the others walk their
        SH lobe. All of them by default. Device data: no kernel is traced again."""
        #: Registry ids of the cosine lobes sampled from the tables.
        self.tabled_ids: set[int] = set(keys) & self.cosine_ids
        flags = np.zeros(max(self._rows.values(), default=0) + 1, dtype=bool)
        for key in self.tabled_ids:
            flags[self._rows[key]] = True
        self._cosine_row = device_array(mi.Bool, flags)

    # -- Host side: fitting ---------------------------------------------------

    def _fit_bsdf(self, bsdf: mi.BSDF, uvs: np.ndarray) -> np.ndarray:
        """Parameters (side, view node, [w_d, w_g, s]) of one BSDF; side 1 is the
        back side (view below the surface), all-zero for one-sided BSDFs. A BSDF of the
        same content fitted before (another scene, object or parameter change, or an
        earlier process) is not fitted again (:mod:`~mitsuba_shsampling.build_cache`)."""
        key = content_key(*content_parts(bsdf), uvs, self.view_cosines)
        return cached_build("lobe_fit", key, lambda: {"params": self._fit_bsdf_now(bsdf, uvs)})["params"]

    def _fit_bsdf_now(self, bsdf: mi.BSDF, uvs: np.ndarray) -> np.ndarray:
        """:meth:`_fit_bsdf` without the cache."""
        if not varies_over_surface(bsdf, uvs):
            uvs = uvs[:1]
        params = np.zeros((2, self.view_nodes, 3))
        params[..., 2] = 1.0
        anisotropic = mi.has_flag(bsdf.flags(), mi.BSDFFlags.Anisotropic)
        sides = [False, True] if mi.has_flag(bsdf.flags(), mi.BSDFFlags.BackSide) else [False]
        # Every side and view node in one search (a kernel a stage).
        g = [mean_mirror_lobe(bsdf, self.view_cosines, uvs, back_side=back,
                              azimuths=ANISOTROPIC_AZIMUTHS if anisotropic else 1) for back in sides]
        views = np.tile(np.arange(self.view_nodes), len(sides))
        fits = fit_two_lobes(g[0] if len(g) == 1 else dr.concat(g), tuple(self.view_cosines), views)
        for index, fit in enumerate(fits):
            params[index // self.view_nodes, index % self.view_nodes] = (fit.diffuse_weight, fit.glossy_weight,
                                                                         fit.exponent)
        return params

    @staticmethod
    def _fit_is_usable(params: np.ndarray) -> bool:
        """Every front-side view node carries positive, finite energy. A lobe
        that evaluates to nothing on the fitting interactions (e.g. a wrapper
        whose ``eval`` needs surface derivatives) would otherwise mark its
        lanes as having no lobe at all, in lanes that are lit."""
        energy = params[0, :, 0] + params[0, :, 1]
        return bool(np.all(np.isfinite(params)) and np.all(energy > 0))

    def _bands_needed(self, params: np.ndarray) -> int:
        """Bands the sharpest significant glossy lobe of one BSDF's table needs."""
        energy = params[..., 0] + params[..., 1]
        glossy = params[..., 1] > MIN_GLOSSY_FRACTION * np.maximum(energy, 1e-30)
        bands = DIFFUSE_BANDS
        for s in params[..., 2][glossy & (energy > 0)]:
            bands = max(bands, bands_for_exponent(s))
        return bands

    # -- Device side: per-lane coefficients -----------------------------------

    def local_normals(self, si: mi.SurfaceInteraction3f, active: mi.Bool = True) -> mi.Vector3f:
        """Per lane, the normal the lobe is oriented about, in ``si.sh_frame``'s local
        coordinates: (0, 0, 1), or a frame-perturbing wrapper's perturbed normal
        (:mod:`.perturbed_frames`). Each wrapper's texture is read in its own lanes only."""
        normal = mi.Vector3f(0.0, 0.0, 1.0)
        if not self._perturbed:
            return normal
        bsdf_id = dr.reinterpret_array(mi.UInt32, si.bsdf())
        with dr.suspend_grad():  # the lobe steers the sampler; it carries no derivatives
            # In the order of the BSDFs' names, not of their creation (which Mitsuba's parallel
            # loading varies): the same kernel in every process.
            for key in sorted(self._perturbed, key=lambda k: self.bsdfs_with_lobes[k].id()):
                key_id, perturbed = self._perturbed[key]
                mine = mi.Bool(active) & (bsdf_id == key_id)
                normal = dr.select(mine, perturbed.local_normal(si, mine), normal)
        return normal

    def _fitted(self, si: mi.SurfaceInteraction3f, active: mi.Bool, normal: mi.Vector3f):
        """:meth:`lookup` before the band-limit clamp of the exponent, for lobes about
        ``normal`` (local to ``si.sh_frame``, :meth:`local_normals`), and each lane's
        table row (0: no lobe)."""
        active = mi.Bool(active) & si.is_valid()
        bsdf_id = dr.reinterpret_array(mi.UInt32, si.bsdf())
        active &= bsdf_id < self._row_of_id_size
        row = dr.gather(mi.UInt32, self._row_of_id, bsdf_id, active)

        cos_view = dr.dot(si.wi, normal)
        side = dr.select(cos_view < 0, mi.UInt32(1), mi.UInt32(0))
        k_last = self.view_nodes - 1
        position = dr.clip((dr.abs(cos_view) - MIN_VIEW_COSINE) / (1.0 - MIN_VIEW_COSINE), 0.0, 1.0) * k_last
        k0 = mi.UInt32(dr.minimum(mi.Int32(position), k_last - 1))
        frac = position - mi.Float(k0)
        base = (row * 2 + side) * self.view_nodes + k0
        p0 = dr.gather(mi.Vector3f, self._table, base, active)
        p1 = dr.gather(mi.Vector3f, self._table, base + 1, active)

        w_d = dr.lerp(p0.x, p1.x, frac)
        w_g = dr.lerp(p0.y, p1.y, frac)
        s = dr.exp(dr.lerp(p0.z, p1.z, frac))
        valid = active & (row > 0) & (w_d + w_g > 0) & dr.isfinite(cos_view) & (cos_view != 0)
        return w_d, w_g, s, valid, row

    def lookup(self, si: mi.SurfaceInteraction3f, active: mi.Bool = True):
        """Interpolated proxy parameters per lane: (w_d, w_g, s, valid).

        ``s`` is already clamped to ``max_exponent``; ``valid`` is False for
        lanes without a fitted lobe (delta, unsupported, no hit, back side of a
        one-sided BSDF, zero energy).
        """
        w_d, w_g, s, valid, _ = self._fitted(si, active, self.local_normals(si, active))
        return w_d, w_g, dr.minimum(s, self.max_exponent), valid

    def coefficients(self, si: mi.SurfaceInteraction3f,
                     grid_from_world: Callable[[mi.Vector3f], mi.Vector3f],
                     active: mi.Bool = True) -> tuple[list, mi.Bool]:
        """SH coefficients of the lobe proxy per lane, in the grid frame.

        Parameter ``si``: the shading point; ``si.wi`` (local, towards the viewer)
        and ``si.sh_frame`` define the lobe, ``si.bsdf()`` its table row.

        Parameter ``grid_from_world``: maps a world direction to the
        environment's grid frame (a rotation; see docs/ARCHITECTURE.md).

        Returns ``(coeffs, use_product)``: ``coeffs`` is a list of ``n_bands**2``
        mi.Float (index l*(l+1)+m), the proxy's integral over the sphere is the
        lobe's energy (directional albedo, luminance) for this view direction;
        ``use_product`` is False for delta, unsupported and invalid lanes, whose
        coefficients are zero. Traceable: no host round trip, one kernel.
        """
        lobes, _, use_product = self.coefficients_and_proxy(si, grid_from_world, active)
        return (lobes.coefficients() if isinstance(lobes, RotatedZonalLobes) else lobes), use_product

    def coefficients_and_proxy(self, si: mi.SurfaceInteraction3f,
                               grid_from_world: Callable[[mi.Vector3f], mi.Vector3f],
                               active: mi.Bool = True, cosine_tables: bool = False,
                               sh_lobes: bool = True) -> tuple[RotatedZonalLobes | list, ProxyLobe | None, mi.Bool]:
        """:meth:`coefficients` in the factored form that the product warps take
        (:class:`~mitsuba_shsampling.sh.zonal.RotatedZonalLobes`: the Phong and the
        diffuse lobe, each about its axis; its contractions cost about half of the
        expanded coefficients', and it needs no n^2 products to build), and the same
        proxy in closed form (:class:`~mitsuba_shsampling.warp.proxy_lobe.ProxyLobe`,
        with the fitted exponent before the band-limit clamp; None without product
        lobes). ``[]`` instead of the lobes where no lane has any (no product lobes in
        the scene, or every lane ``cosine_only``).

        With ``cosine_tables`` (the product warp samples clamped cosines from its
        tables), the lanes of a cosine lobe (:func:`is_cosine_lobe`) are marked
        ``cosine_only`` in the proxy and get no coefficients (zeros): their SH
        expansion is not computed. ``sh_lobes`` False says that every ``active``
        lane has a cosine lobe (the caller knows it from the materials it asks
        for): ``cosine_only`` is then the constant True and no SH code is traced
        (no coefficients)."""
        if not self.has_product_lobes:
            return [], None, mi.Bool(False)
        local_normal = self.local_normals(si, active)
        w_d, w_g, s_fitted, use_product, row = self._fitted(si, active, local_normal)
        cosine_tables = cosine_tables and self.has_cosine_lobes
        if cosine_tables and not sh_lobes:
            cosine_only = True
        elif cosine_tables:
            cosine_only = dr.gather(mi.Bool, self._cosine_row, row, use_product) & use_product
        else:
            cosine_only = False  # no lane: the product warp traces no table code
        s = dr.minimum(s_fitted, self.max_exponent)

        wi = si.wi
        cos_view = dr.dot(wi, local_normal)
        side = dr.select(cos_view < 0, -1.0, 1.0)
        normal = grid_from_world(si.to_world(local_normal * side))
        mirror = grid_from_world(si.to_world(dr.fma(local_normal, 2.0 * cos_view, -wi)))

        cosine = clamped_cosine_attenuation(min(DIFFUSE_BANDS, self.n_bands))

        def rotated_lobes(w_d, w_g, s, normal, mirror):
            return rotate_zonal_lobes([([w_g * lam for lam in phong_attenuation(s, self.n_bands)], mirror),
                                       ([w_d * (lam / cosine[0]) for lam in cosine], normal)])

        def no_lobes(*_):
            return RotatedZonalLobes.zeros([self.n_bands, len(cosine)])

        # A symbolic branch: packets without a product lane skip the basis evaluation.
        coeffs = [] if cosine_only is True else dr.if_stmt(
            args=(w_d, w_g, s, normal, mirror), cond=mi.Bool(use_product) & ~mi.Bool(cosine_only),
            true_fn=rotated_lobes, false_fn=no_lobes)
        proxy = ProxyLobe(normal, dr.select(use_product, w_d, 0.0), mirror,
                          dr.select(use_product, w_g, 0.0), s_fitted, cosine_only)
        return coeffs, proxy, use_product
