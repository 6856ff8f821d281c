"""Any Mitsuba scene, set up for a comparison: its own camera on a new film and sampler.

``compare`` must run unmodified scenes, so nothing here relies on ``$res``,
``$spp`` or ``$sampler`` defaults. The scene is loaded as written; then

- the **sensor is built again** from the scene's camera parameters
  (``mi.traverse``: ``to_world``, ``x_fov``, clip planes, principal point, lens)
  with an ``hdrfilm`` of the comparison's width (the scene's aspect ratio and
  reconstruction filter kept) and the comparison's sampler; renders pass it as
  ``mi.render(scene, sensor=...)``, so the sampler a report names is the one that ran;
- the **environment map is rebuilt** only when a method or ``--envmap`` asks for it
  (MIS compensation, another map): same ``to_world`` and ``scale``, the scene's
  other shapes and emitters reused as they are (``render --envmap`` uses the same code).

:func:`content_digest` keys the reference cache on what the image depends on:
every file the scene references (by content) and every traversed parameter value.
"""

from __future__ import annotations

import hashlib
import os
import re
import xml.etree.ElementTree as ET

import numpy as np

import mitsuba as mi

from ..envmap.emitter import envmap_like
from ..scenes import SceneError, scene_envmap
from ..traversal import readable_parameters

#: Camera plugins whose parameters :func:`comparison_sensor` can carry over.
SUPPORTED_CAMERAS = {"PerspectiveCamera": "perspective", "ThinLensCamera": "thinlens",
                     "OrthographicCamera": "orthographic"}


def _scalar(value) -> float:
    return float(np.array(value).ravel()[0])


def _transform(value) -> mi.ScalarTransform4f:
    matrix = np.array(value.matrix, dtype=np.float64)
    return mi.ScalarTransform4f(matrix[..., 0] if matrix.ndim == 3 else matrix)


def comparison_sensor(scene: mi.Scene, width: int, sampler: str, spp: int) -> mi.Sensor:
    """The scene's first camera, rebuilt with a ``width``-pixel film and a ``sampler`` at ``spp``.

    Height follows the scene film's aspect ratio; the film's reconstruction filter is reused.
    :raises SceneError: the scene has no sensor, or one of another kind than
        :data:`SUPPORTED_CAMERAS`.
    """
    if not scene.sensors():
        raise SceneError("the scene has no sensor to render from")
    sensor = scene.sensors()[0]
    kind = SUPPORTED_CAMERAS.get(sensor.class_name())
    if kind is None:
        raise SceneError(f"compare renders perspective, thin-lens and orthographic cameras; this "
                         f"scene's sensor is a {sensor.class_name()}")
    params = mi.traverse(sensor)
    film = sensor.film()
    size = film.size()
    height = max(1, round(width * int(size[1]) / int(size[0])))
    desc = {
        "type": kind,
        "to_world": _transform(params["to_world"]),
        "near_clip": _scalar(params["near_clip"]),
        "far_clip": _scalar(params["far_clip"]),
        "film": {"type": "hdrfilm", "width": width, "height": height, "pixel_format": "rgb",
                 "rfilter": film.rfilter()},
        "sampler": {"type": sampler, "sample_count": spp},
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


def with_environment(scene: mi.Scene, filename: str | None = None,
                     mis_compensation: bool = False) -> mi.Scene:
    """``scene`` with its envmap rebuilt from ``filename`` (None: the same texels) and
    ``mis_compensation``; ``to_world`` and ``scale`` are kept, and so are the scene's other
    emitters, shapes, sensors and integrator (``render --envmap`` renders with it).

    :raises SceneError: the scene has no ``envmap`` emitter.
    """
    env = scene_envmap(scene)
    if env is None:
        raise SceneError("the scene has no envmap emitter to replace or compensate")
    replacement = envmap_like(env, filename, mis_compensation)
    # Emitters keep their order (the new envmap takes the old one's place), so that a seed
    # draws the same emitter choices as in the original scene.
    objects = {"type": "scene"}
    if scene.integrator() is not None:
        objects["integrator"] = scene.integrator()
    for i, emitter in enumerate(scene.emitters()):
        if emitter is env:
            objects[f"emitter_{i}"] = replacement
        elif emitter.get_shape() is None:
            objects[f"emitter_{i}"] = emitter
    for i, shape in enumerate(scene.shapes()):
        # Keyed by the shape's own id where it has one: load_dict names an object after its
        # key, and reports name materials after their shapes.
        key = shape.id() if shape.id() and shape.id() not in objects else f"shape_{i}"
        objects[key] = shape  # carries its BSDF and area emitter
    for i, sensor in enumerate(scene.sensors()):
        objects[f"sensor_{i}"] = sensor
    return mi.load_dict(objects)


def referenced_files(scene_path: str, overrides: dict[str, str] | None = None) -> list[str]:
    """The scene file, every file it includes, and every existing file a ``filename`` names.

    ``$name`` references are resolved with the scene's ``<default>`` values and ``overrides``;
    relative paths against the referencing file's folder, then the main scene's folder (as
    Mitsuba's file resolver does).
    """
    root_dir = os.path.dirname(os.path.abspath(scene_path))
    seen: list[str] = []

    def visit(path: str, params: dict[str, str]) -> None:
        path = os.path.abspath(path)
        if path in seen:
            return
        seen.append(path)
        try:
            root = ET.parse(path).getroot()
        except (ET.ParseError, OSError):
            return
        params = {**{d.get("name"): d.get("value") for d in root.iter("default")}, **params}
        for element in root.iter():
            if element.tag == "include":
                name = element.get("filename")
            elif element.get("name") == "filename":
                name = element.get("value")
            else:
                continue
            if not name:
                continue
            name = re.sub(r"\$(\w+)", lambda m: params.get(m.group(1), m.group(0)), name)
            for folder in (os.path.dirname(path), root_dir):
                candidate = os.path.join(folder, name)
                if os.path.isfile(candidate):
                    if element.tag == "include" or candidate.endswith(".xml"):
                        visit(candidate, params)
                    elif os.path.abspath(candidate) not in seen:
                        seen.append(os.path.abspath(candidate))
                    break

    visit(scene_path, dict(overrides or {}))
    return seen


def _value_bytes(value) -> bytes:
    """The numbers of a traversed parameter (a transform by its matrix, not its address)."""
    if hasattr(value, "matrix"):
        value = value.matrix
    array = np.asarray(value)
    if array.dtype == object:
        # No numeric form: its repr may name an address, which only costs a cache miss.
        return repr(value).encode()
    return np.ascontiguousarray(array).tobytes()


def content_digest(scene_path: str, scene: mi.Scene, extra_files: list[str] = ()) -> str:
    """SHA-256 over the bytes of every referenced file and every traversed parameter value.

    Either alone would miss something: parameters cover data read by plugins but not their
    non-differentiable settings (a BSDF's microfacet distribution), the XML covers those.
    Object names Mitsuba invents from memory addresses (``object_1403...``) are dropped.
    """
    digest = hashlib.sha256()
    for path in referenced_files(scene_path) + [os.path.abspath(f) for f in extra_files]:
        digest.update(os.path.basename(path).encode())
        with open(path, "rb") as f:
            for block in iter(lambda: f.read(1 << 20), b""):
                digest.update(block)
    # Ties between renamed keys keep the traversal order, which is the scene's own.
    entries = sorted((re.sub(r"object_\d+", "object", key), i, value)
                     for i, (key, value) in enumerate(readable_parameters(mi.traverse(scene))))
    for stable_key, _, value in entries:
        digest.update(stable_key.encode())
        digest.update(_value_bytes(value))
    return digest.hexdigest()
