"""Synthetic latitude-longitude environment maps for tests and benchmarks.

All images use the layout of Mitsuba's ``envmap`` emitter: array shape
(H, W, 3), linear RGB radiance, row ``y`` at polar angle ``theta = y pi / (H-1)``
measured from the local +Y axis, column ``x`` centred at ``u = (x + 0.5) / W``
with local direction ``(sin(2 pi u) sin(theta), cos(theta), -cos(2 pi u) sin(theta))``.
"""

from __future__ import annotations

import numpy as np


def constant_latlong(height: int, width: int, value: float = 1.0) -> np.ndarray:
    """Uniform grey map of radiance ``value``, shape (H, W, 3), float32."""
    return np.full((height, width, 3), value, dtype=np.float32)


def sun_sky_latlong(height: int, width: int, sun_direction=(0.3, 0.8, -0.5),
                    sun_radius_deg: float = 0.5, sun_radiance: float = 1e5,
                    sky_radiance: float = 1.0) -> np.ndarray:
    """Smooth bluish sky plus a tiny, very bright sun, shape (H, W, 3), float32.

    The sun covers every texel centre within ``sun_radius_deg`` of
    ``sun_direction`` (local +Y-up frame, normalised here) and at least the
    texel nearest to it, so it never vanishes at low resolution. The sky is
    brighter near the local zenith (+Y) and dim below the horizon, so the map
    has both a smooth part and a feature far below the texel scale of a
    coarse grid: the hard case for resampling and for samplers.
    """
    sun = np.asarray(sun_direction, dtype=np.float64)
    sun = sun / np.linalg.norm(sun)
    # Separable in (row, column): no (H, W, 3) float64 temporaries for 8k maps.
    theta = np.arange(height) * np.pi / max(height - 1, 1)
    u = (np.arange(width) + 0.5) / width
    st, ct = np.sin(theta)[:, None], np.cos(theta)[:, None]
    sp, cp = np.sin(2 * np.pi * u)[None, :], np.cos(2 * np.pi * u)[None, :]
    cos_to_sun = (st * (sp * sun[0] - cp * sun[2]) + ct * sun[1]).astype(np.float32)

    sky = (sky_radiance * (0.1 + 0.9 * np.clip(np.cos(theta), 0.0, 1.0))).astype(np.float32)
    image = np.empty((height, width, 3), dtype=np.float32)
    image[:] = sky[:, None, None] * np.array([0.6, 0.8, 1.0], dtype=np.float32)
    in_sun = cos_to_sun >= np.cos(np.radians(sun_radius_deg))
    in_sun.flat[np.argmax(cos_to_sun)] = True
    image[in_sun] = sun_radiance * np.array([1.0, 0.95, 0.85], dtype=np.float32)
    return image


def window_latlong(height: int, width: int, direction=(0.3, 0.8, 0.5), exponent: float = 6.0,
                   peak: float = 40.0, ambient: float = 1.0) -> np.ndarray:
    """A smooth interior-like light: ``ambient`` everywhere plus a broad bright
    lobe ``peak * max(cos, 0)^exponent`` about ``direction`` (local +Y-up frame),
    shape (H, W, 3), float32. No feature below the texel scale: the map where
    a glossy lobe meets a broad bright region."""
    axis = np.asarray(direction, dtype=np.float64)
    axis = axis / np.linalg.norm(axis)
    theta = (np.arange(height) + 0.5) * np.pi / height
    phi = (np.arange(width) + 0.5) * 2 * np.pi / width
    st, ct = np.sin(theta)[:, None], np.cos(theta)[:, None]
    cosine = st * (np.sin(phi)[None, :] * axis[0] - np.cos(phi)[None, :] * axis[2]) + ct * axis[1]
    radiance = ambient + peak * np.clip(cosine, 0.0, 1.0) ** exponent
    return np.repeat(radiance[..., None], 3, axis=-1).astype(np.float32)


def envmap_emitter(image: np.ndarray, scale: float = 1.0, to_world=None):
    """Mitsuba ``envmap`` emitter holding ``image`` (H, W, 3) as radiance.

    ``to_world`` is an optional ``mi.ScalarAffineTransform4f``. Needs a
    Mitsuba variant to be set.
    """
    import mitsuba as mi

    desc = {"type": "envmap", "bitmap": mi.Bitmap(np.ascontiguousarray(image, dtype=np.float32)),
            "scale": float(scale)}
    if to_world is not None:
        desc["to_world"] = to_world
    return mi.load_dict(desc)
