"""The product strategy of an environment whose pyramid leaves a sun out.

An evaluated ``sunsky`` (:mod:`~mitsuba_shsampling.envmap.evaluated`) has its sky in the
pyramid and its sun nowhere in it: the product of the lobe and the sky reaches the sun's
disc only at the sky's density there. Each lane samples the mixture

    q = (1 - s) p_product + s p_emitter,

with ``p_emitter`` the emitter's own sampling (which draws the sun's disc exactly, and the
sky), so q reaches every direction the emitter lights at a density >= s p_emitter, whatever
the pyramid holds. One 2D sample, one direction, one shadow ray: the first coordinate picks
the part and is rescaled, so that the part gets a uniform sample.

The share is the lane's: its lobe proxy's estimate of the sun's share of what it reflects,

    s = w_sun / (w_sun + w_sky),  w_sun = P_sun q(w_sun),  w_sky = (w_d + w_g) L_sky,

(``P_sun`` the sun's luminance x solid angle, ``q`` the proxy lobe, ``w_d + w_g`` its
integral, ``L_sky`` the sky's mean radiance), within [:data:`MIN_EMITTER_SHARE`,
:data:`MAX_EMITTER_SHARE`]. A lobe that faces away from the sun gives nearly every sample
to the product of the sky; a diffuse surface in the sun gives most to the emitter. The
share depends only on the lane's lobe, so :meth:`SkyMixture.pdf` computes the same one.
Measured on a sphere scene under Mitsuba's default ``sunsky`` (16 passes of 16 spp), one
fixed share was no good: at 0.5 the product had 2.7x the variance of the environment
alone, at 0.95 1.1x.
"""

from __future__ import annotations

import math

import drjit as dr
import mitsuba as mi

#: Bounds of a lane's share of the emitter's own sampling: at least enough that a sun outside
#: the proxy lobe (which is only a proxy) is still drawn, at most enough that the product
#: keeps some samples of the sky where the sun dominates.
MIN_EMITTER_SHARE, MAX_EMITTER_SHARE = 0.1, 0.95


class SkyMixture:
    """``warp`` (a :class:`~.product.ProductWarp` of the sky's pyramid) mixed with the
    emitter's own sampling (``directions``:
    :class:`~mitsuba_shsampling.envmap.emitter.EmitterDirections`) at each lane's share of
    the sun, at grid-frame direction ``sun`` with luminance power ``sun_power``
    (radiance x sr); ``sky_total`` is the pyramid's integral. ``sample`` and ``pdf`` have
    the warp's signatures; every other attribute is the warp's (its pyramid, its cosine
    tables)."""

    def __init__(self, warp, directions, sun, sun_power: float, sky_total: float, sun_sampling_share: float = 1.0):
        if not (sun_power > 0 and sky_total > 0):
            raise ValueError(f"SkyMixture: needs a sun and a sky, got powers {sun_power} and {sky_total}")
        self.warp, self.directions = warp, directions
        # Opaque: a sun that moves (an optimisation, an animation) changes no kernel.
        sun = dr.normalize(mi.ScalarVector3f(sun))
        self.sun = mi.Vector3f(*(dr.opaque(mi.Float, float(c)) for c in sun))
        self.sun_power = dr.opaque(mi.Float, float(sun_power))
        self.sky_radiance = dr.opaque(mi.Float, float(sky_total) / (4.0 * math.pi))
        # The emitter's own sampling puts this share of its samples on the sun: a lane whose
        # sun share is w needs w / this of them from the emitter.
        self.sun_sampling_share = dr.opaque(mi.Float, float(sun_sampling_share))
        #: The share of lanes without a proxy lobe: the sun's share of the power.
        self.fixed_share = dr.opaque(mi.Float, min(max(float(sun_power) / (float(sun_power) + float(sky_total)),
                                                       MIN_EMITTER_SHARE), MAX_EMITTER_SHARE))

    def __getattr__(self, name):
        return getattr(self.warp, name)

    def share(self, proxy) -> mi.Float:
        """The emitter's share ``s`` of each lane (module docstring)."""
        if proxy is None:
            return mi.Float(self.fixed_share)
        sun = self.sun_power * proxy.value(self.sun)
        sky = (proxy.diffuse_weight + proxy.glossy_weight) * self.sky_radiance
        s = sun / ((sun + sky) * self.sun_sampling_share)
        return dr.select(dr.isfinite(s), dr.clip(s, MIN_EMITTER_SHARE, MAX_EMITTER_SHARE), self.fixed_share)

    def sample(self, coeffs, u: mi.Point2f, proxy=None):
        """(world direction, pdf of the mixture) for ``u`` in [0, 1)^2."""
        s = self.share(proxy)
        own = u.x < s
        u_own = mi.Point2f(dr.minimum(u.x / s, dr.one_minus_epsilon(mi.Float)), u.y)
        u_product = mi.Point2f(dr.minimum((u.x - s) / (1.0 - s), dr.one_minus_epsilon(mi.Float)), u.y)
        # Each part's sample returns its own pdf; the other part's is evaluated at that
        # direction. Symbolic branches: a packet whose lanes all took one part runs one walk.
        d, chosen = dr.if_stmt(args=(coeffs, u_own, u_product, proxy), cond=own,
                               true_fn=lambda c, a, b, p: self.directions.sample(a),
                               false_fn=lambda c, a, b, p: self.warp.sample(c, b, p))
        other = dr.if_stmt(args=(coeffs, d, proxy), cond=own,
                           true_fn=lambda c, v, p: self.warp.pdf(c, v, p),
                           false_fn=lambda c, v, p: self.directions.pdf(v))
        product_pdf, own_pdf = dr.select(own, other, chosen), dr.select(own, chosen, other)
        return d, dr.fma(1.0 - s, product_pdf, s * own_pdf)

    def pdf(self, coeffs, d: mi.Vector3f, proxy=None) -> mi.Float:
        """Density of :meth:`sample` at world direction ``d``."""
        s = self.share(proxy)
        return dr.fma(1.0 - s, self.warp.pdf(coeffs, d, proxy), s * self.directions.pdf(d))
