"""Environment emitters that are not an ``envmap``: their pyramid from their own radiance.

Mitsuba's ``sunsky`` and ``constant`` emitters have no texels to read. Their radiance is
evaluated instead, in one kernel, at the texel centres of a lat-long image in the
``envmap`` layout (row 0 at the world +Y pole, u = atan2(d.x, -d.z) / 2 pi), and the
pyramid is built from that image (:meth:`~.pyramid.EnvPyramid.from_latlong`, identity
``to_world``: the directions are world directions already). The estimators evaluate the
emitter itself, so the image is only a sampling density: it need not be exact, only
positive where the radiance is.

What such an image can resolve is smooth: the sky. The sun of a ``sunsky`` (a disc of half a
degree, radiance 10^4-10^5 times the sky's) is not in the image (it is evaluated with
``sun_scale`` set to 0 for the duration) but in :class:`SkyComponents.sun_power`: the
product strategy then samples a mixture that gives the emitter's own sampling (which draws
the sun exactly) a share of the samples (:class:`~mitsuba_shsampling.warp.sky_mixture.SkyMixture`).
"""

from __future__ import annotations

from typing import NamedTuple

import drjit as dr
import mitsuba as mi
import numpy as np

#: Class names of the environment emitters built this way, with the user's plugin name.
EVALUATED_EMITTERS = {"SunskyEmitter": "sunsky", "ConstantBackgroundEmitter": "constant"}

#: Width of the evaluated image (its height is half of it): 0.7 degrees a texel, finer
#: than the sky models' features (the sun's aureole spans degrees); the pyramid's subtexel
#: levels and its trimming then pick the depth. A 1024-wide image took 1.2 s more to build.
IMAGE_WIDTH = 512

#: Emitter samples of the estimate of the emitter's whole integral (:func:`sky_components`):
#: the emitter's own sampling is close to proportional to its radiance, so the estimate's
#: relative error is a few tenths of a percent; it only sets a mixture share.
INTEGRAL_SAMPLES = 1 << 16


def is_evaluated(emitter: mi.Emitter | None) -> bool:
    """``emitter`` is an environment this package samples through its evaluated radiance."""
    return emitter is not None and emitter.class_name() in EVALUATED_EMITTERS


class SkyComponents(NamedTuple):
    """What the sampling of an evaluated environment is built from."""

    image: np.ndarray
    """(H, W) luminance of the smooth part (the sky), lat-long, in the world frame."""
    sun_power: float
    """Luminance integral (radiance x sr) of what the image leaves out (the sun), >= 0."""
    sun: mi.ScalarVector3f | None
    """World direction of the sun (None: the image leaves nothing out)."""
    total: float
    """Luminance integral of the whole emitter (the emitter's own sampling's estimate)."""
    sun_sampling_share: float = 1.0
    """Share of the emitter's own samples that land on the sun (radiance above the image's
    brightest texel): how much of a mixture's emitter part reaches it."""


def latlong_directions(width: int, height: int) -> mi.Vector3f:
    """World directions of the texel centres of a ``width`` x ``height`` lat-long image in
    the ``envmap`` layout (row-major)."""
    x, y = dr.meshgrid(dr.arange(mi.Float, width), dr.arange(mi.Float, height))
    phi, theta = (x + 0.5) * (dr.two_pi / width), (y + 0.5) * (dr.pi / height)
    sin_theta = dr.sin(theta)
    return mi.Vector3f(sin_theta * dr.sin(phi), dr.cos(theta), -sin_theta * dr.cos(phi))


def radiance_luminance(emitter: mi.Emitter, d: mi.Vector3f) -> mi.Float:
    """Luminance of the radiance ``emitter`` sends along -``d`` (arriving from ``d``); in
    spectral variants the mean over the fixed wavelengths the lobes are fitted at."""
    from ..lobes.fit import fit_wavelengths, luminance  # the lobe fits' convention of a scalar weight
    si = dr.zeros(mi.SurfaceInteraction3f)
    si.wi = -d
    if mi.is_spectral:
        si.wavelengths = fit_wavelengths()
    return luminance(emitter.eval(si))


def _sun_scale_set_to(emitter: mi.Emitter, value: float | None):
    """Set a ``sunsky``'s ``sun_scale`` (None: leave it); returns the old value."""
    params = mi.traverse(emitter)
    if "sun_scale" not in params or value is None:
        return None
    old = float(params["sun_scale"])
    params["sun_scale"] = value
    params.update()
    return old


def sky_components(emitter: mi.Emitter, width: int = IMAGE_WIDTH) -> SkyComponents:
    """The evaluated image of ``emitter``'s smooth part and the power of the rest.

    The whole emitter's integral is estimated with its own sampling (``sample_direction``,
    :data:`INTEGRAL_SAMPLES` stratified samples); what the image does not hold of it is the
    sun's. A ``sunsky`` is evaluated without its sun and given back its ``sun_scale``
    afterwards, also when the evaluation fails."""
    height = max(width // 2, 1)
    total, samples = _emitter_integral(emitter)
    old = _sun_scale_set_to(emitter, 0.0)
    try:
        image = np.broadcast_to(radiance_luminance(emitter, latlong_directions(width, height)).numpy(),
                                (height * width,)).reshape(height, width)  # a constant's is one value
    finally:
        _sun_scale_set_to(emitter, old)
    image = np.where(np.isfinite(image) & (image > 0), image, 0.0).astype(np.float32)
    # The image's integral: texels are equal in (u, theta), their solid angle is sin(theta) du dtheta.
    theta = (np.arange(height) + 0.5) * (np.pi / height)
    sky = float(np.sum(image.astype(np.float64) * np.sin(theta)[:, None]) * (2 * np.pi / width) * (np.pi / height))
    sun = total - sky if old else 0.0
    if not sun > 1e-3 * total:  # what is left of the estimate without a sun is its noise, not light
        return SkyComponents(image, 0.0, None, total)
    direction = dr.ravel(mi.traverse(emitter)["sun_direction"]).numpy()
    on_sun = float(np.mean(samples > 2.0 * image.max()))
    return SkyComponents(image, sun, mi.ScalarVector3f(*map(float, direction)), total, max(on_sun, 1e-3))


def _emitter_integral(emitter: mi.Emitter) -> tuple[float, np.ndarray]:
    """Luminance integral of ``emitter`` over the sphere, the mean of radiance / pdf over
    stratified samples of its own sampling (radiance x sr), and the radiance (luminance)
    of those samples."""
    side = int(np.sqrt(INTEGRAL_SAMPLES))
    x, y = dr.meshgrid(dr.arange(mi.Float, side), dr.arange(mi.Float, side))
    u = mi.Point2f((x + 0.5) / side, (y + 0.5) / side)
    ds, _ = emitter.sample_direction(dr.zeros(mi.Interaction3f), u)
    value = radiance_luminance(emitter, ds.d)
    ratio = dr.select((ds.pdf > 0) & dr.isfinite(value), value / ds.pdf, 0.0)
    return float(np.mean(ratio.numpy(), dtype=np.float64)), np.broadcast_to(value.numpy(), (side * side,))
