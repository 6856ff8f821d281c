"""A scene's camera built again on another film: the same view at another resolution.

Used where a render must cover the same image as the user's camera with other pixels:
``compare`` renders every method on a film of the comparison's width, and the plan's
pilot passes render a film a whole factor coarser than a large one (their statistic
needs a fixed number of camera samples, not one per pixel). The camera's parameters are
read with ``mi.traverse`` (``to_world``, ``x_fov``, clip planes, principal point, lens);
the reconstruction filter is the film's own.
"""

from __future__ import annotations

import mitsuba as mi
import numpy as np

SUPPORTED_CAMERAS = {"PerspectiveCamera": "perspective", "ThinLensCamera": "thinlens",
                     "OrthographicCamera": "orthographic"}
"""Camera plugins whose parameters :func:`camera_on_film` carries over (class name -> plugin)."""


def _scalar(value) -> float:
    return float(np.array(value).ravel()[0])


def _transform(value) -> mi.ScalarTransform4f:
    matrix = np.array(value.matrix, dtype=np.float64)
    return mi.ScalarTransform4f(matrix[..., 0] if matrix.ndim == 3 else matrix)


def camera_on_film(sensor: mi.Sensor, width: int, height: int, sampler) -> mi.Sensor:
    """``sensor``'s camera on a ``width`` x ``height`` ``hdrfilm`` (RGB, the film's filter),
    sampling with ``sampler`` (a plugin description or a :class:`mi.Sampler`).

    :raises ValueError: a camera of another kind than :data:`SUPPORTED_CAMERAS`.
    """
    kind = SUPPORTED_CAMERAS.get(sensor.class_name())
    if kind is None:
        raise ValueError(f"a {sensor.class_name()} camera cannot be built again (supported: "
                         f"{', '.join(SUPPORTED_CAMERAS.values())})")
    params = mi.traverse(sensor)
    desc = {
        "type": kind,
        "to_world": _transform(params["to_world"]),
        "near_clip": _scalar(params["near_clip"]),
        "far_clip": _scalar(params["far_clip"]),
        "film": {"type": "hdrfilm", "width": int(width), "height": int(height), "pixel_format": "rgb",
                 "rfilter": sensor.film().rfilter()},
        "sampler": sampler,
    }
    if kind in ("perspective", "thinlens"):
        desc.update(fov=_scalar(params["x_fov"]), fov_axis="x")
    if kind == "perspective":
        desc.update(principal_point_offset_x=_scalar(params["principal_point_offset_x"]),
                    principal_point_offset_y=_scalar(params["principal_point_offset_y"]))
    if kind == "thinlens":
        desc.update(aperture_radius=_scalar(params["aperture_radius"]),
                    focus_distance=_scalar(params["focus_distance"]))
    return mi.load_dict(desc)
