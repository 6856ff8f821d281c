"""Environment emitters that are not an ``envmap``: their pyramid from their own radiance.

Mitsuba's ``sunsky`` and ``constant`` emitters have no texels to read. Their radiance is
evaluated instead, in one kernel, at the texel centres of a lat-long image in the
``envmap`` layout (row 0 at the world +Y pole, u = atan2(d.x, -d.z) / 2 pi), and the
pyramid is built from that image (:meth:`~.pyramid.EnvPyramid.from_latlong`, identity
``to_world``: the directions are world directions already). The estimators evaluate the
emitter itself, so the image is only a sampling density: it need not be exact, only
positive where the radiance is.

What such an image can resolve is smooth: the sky. The sun of a ``sunsky`` (a disc of half a
degree, radiance 10^4-10^5 times the sky's) is not in the image (a copy without its sun is
evaluated) but in :class:`SkyComponents.sun_power`: the
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


def _value(params: mi.SceneParameters, key: str):
    """A traversed parameter as a Python float, or a list of floats (RGB)."""
    values = np.ravel(np.asarray(params[key], dtype=np.float64))
    return float(values[0]) if values.size == 1 else [float(v) for v in values]


def _option(described: str, label: str, default: str) -> str:
    """The value after ``label =`` in a plugin's description (its ``str``), else ``default``."""
    for line in described.splitlines():
        if line.strip().startswith(label + " ="):
            return line.split("=", 1)[1].strip()
    return default


def _sunsky_copy(emitter: mi.Emitter, with_sun: bool) -> mi.Emitter:
    """A ``sunsky`` with ``emitter``'s sky (its sun's world direction, turbidity, albedo,
    scales and ``to_world``; with its sun, or without: ``sun_scale`` 0).

    The set-up evaluates copies, never the scene's emitter: with the scene's own sunsky
    evaluated in kernels of their own before the first render, a later render of a second
    sunsky scene in the same process aborted in Dr.Jit's LLVM backend ("invalid redefinition
    of function", the ``Emitter::eval`` callable emitted twice into one kernel; a copy
    evaluated in its place did not). The sun's aperture and model are not traversable; they
    are read from the emitter's description (they only size the sun's power estimate)."""
    params = mi.traverse(emitter)
    albedo = _value(params, "albedo.value")
    described = str(emitter)
    return mi.load_dict({
        "type": "sunsky", "sun_direction": _value(params, "sun_direction"),
        "turbidity": _value(params, "turbidity"), "sky_scale": _value(params, "sky_scale"),
        "sun_scale": _value(params, "sun_scale") if with_sun else 0.0,
        "albedo": {"type": "rgb", "value": albedo} if isinstance(albedo, list) else albedo,
        "sun_aperture": float(_option(described, "Sun aperture", "0.5358")),
        "complex_sun": _option(described, "Complex sun model", "false") == "true",
        "to_world": mi.ScalarTransform4f(np.asarray(params["to_world"].matrix.numpy())[..., 0]),
    })


def _constant_luminance(emitter: mi.Emitter) -> float | None:
    """A ``constant`` emitter's luminance read on the host (None where its radiance is not
    a plain RGB or grey value: it is then evaluated in a kernel)."""
    params = mi.traverse(emitter)
    if "radiance.value" not in params or mi.is_spectral:
        return None
    value = _value(params, "radiance.value")
    return float(np.dot(value, [0.212671, 0.715160, 0.072169])) if isinstance(value, list) else value


def sky_components(emitter: mi.Emitter, width: int = IMAGE_WIDTH) -> SkyComponents:
    """The evaluated image of ``emitter``'s smooth part and the power of the rest.

    A ``sunsky``'s image is that of a copy without its sun (:func:`_sunsky_copy`); the
    whole emitter's integral is estimated with a copy's own sampling (``sample_direction``,
    :data:`INTEGRAL_SAMPLES` stratified samples), and what the image does not hold of it is
    the sun's. A ``constant``'s image is its luminance, read on the host."""
    height = max(width // 2, 1)
    theta = (np.arange(height) + 0.5) * (np.pi / height)
    constant = _constant_luminance(emitter) if emitter.class_name() == "ConstantBackgroundEmitter" else None
    if constant is not None:
        image = np.full((height, width), max(constant, 0.0) if np.isfinite(constant) else 0.0, np.float32)
        total, samples, has_sun = 4 * np.pi * float(image[0, 0]), None, False
    else:
        has_sun = emitter.class_name() == "SunskyEmitter"
        whole = _sunsky_copy(emitter, with_sun=True) if has_sun else emitter
        total, samples = _emitter_integral(whole)
        sky = _sunsky_copy(emitter, with_sun=False) if has_sun else emitter
        image = np.broadcast_to(radiance_luminance(sky, latlong_directions(width, height)).numpy(),
                                (height * width,)).reshape(height, width)
        image = np.where(np.isfinite(image) & (image > 0), image, 0.0).astype(np.float32)
    # The image's integral: texels are equal in (u, theta), their solid angle is sin(theta) du dtheta.
    sky_total = float(np.sum(image.astype(np.float64) * np.sin(theta)[:, None]) * (2 * np.pi / width)
                      * (np.pi / height))
    sun = total - sky_total if has_sun else 0.0
    if not sun > 1e-3 * total:  # what is left of the estimate without a sun is its noise, not light
        return SkyComponents(image, 0.0, None, total)
    direction = _value(mi.traverse(emitter), "sun_direction")
    on_sun = float(np.mean(samples > 2.0 * image.max()))
    return SkyComponents(image, sun, mi.ScalarVector3f(*direction), total, max(on_sun, 1e-3))


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
