"""Built-in scenes and environment maps, and a loader that sets their parameters.

The scenes are this package's data, beside this file (so an installed package
has them): Mitsuba 3 XML files, a shared stage in ``include/`` and the maps in
``textures/``. Their settings are ``<default name=...>`` parameters:

================== =========================================================
``envmap``         lat-long map file of the ``envmap`` emitter
``mis_compensation`` ``true``/``false``: the envmap's MIS compensation
``res``            image width (pixels); also the height, unless the scene declares
                   ``height``, which then follows ``res`` at the scene's default aspect
``spp``            samples per pixel of the sensor's sampler
``sampler``        sampler plugin (``independent``, ``stratified``, ...)
``integrator``     integrator plugin used by ``mi.load_file`` alone
================== =========================================================

The integrator is normally supplied at render time
(``mi.render(scene, integrator=...)``), so one scene serves every method.
A scene may declare only some of these (``area_light.xml`` has no envmap);
:func:`load_scene` passes only the parameters a scene declares, because
Mitsuba rejects unused ones.
"""

from __future__ import annotations

import os
import xml.etree.ElementTree as ET

import mitsuba as mi

#: Folder of the built-in XML scenes.
SCENES_DIR = os.path.dirname(os.path.abspath(__file__))
#: Folder of the built-in environment maps.
TEXTURES_DIR = os.path.join(SCENES_DIR, "textures")
#: Mitsuba's ``sunsky`` (Hosek-Wilkie sky + sun 35 degrees up) baked by scripts/bake_sunsky.py.
SUNSKY_MAP = os.path.join(TEXTURES_DIR, "sunsky.exr")
#: Three softboxes on a dim room, made by scripts/make_studio_envmap.py.
STUDIO_MAP = os.path.join(TEXTURES_DIR, "studio.exr")

#: The scene ``compare`` renders when given none: realistic, so that its verdict is one a user can expect.
DEFAULT_SCENE = "material_studio"
#: The glossy unit case (one GGX sphere on a ground plane) of tests and sampler benchmarks.
UNIT_SCENE = "sphere_ggx010"


class SceneError(ValueError):
    """A scene file is missing, unreadable, or lacks a requested parameter."""


def builtin_scenes() -> dict[str, str]:
    """Name (file stem) -> absolute path of every built-in scene, sorted by name."""
    names = sorted(f for f in os.listdir(SCENES_DIR) if f.endswith(".xml"))
    return {f[:-4]: os.path.join(SCENES_DIR, f) for f in names}


def builtin_envmaps() -> dict[str, str]:
    """Name (file stem) -> absolute path of the environment maps shipped in ``textures/``."""
    names = sorted(f for f in os.listdir(TEXTURES_DIR) if f.endswith((".exr", ".hdr")))
    return {os.path.splitext(f)[0]: os.path.join(TEXTURES_DIR, f) for f in names}


def default_scene_path() -> str:
    """The scene ``compare`` renders when given none: the material studio under the sun-and-sky map.

    Ten materials on a textured ground, a 115k-triangle mesh and the default Gaussian film filter
    (``scripts/make_scenes.py``): most of its pixels are ground and diffuse or fallback materials,
    as in the scenes users render, so its verdict is not the best case of a glossy sphere.
    """
    return builtin_scenes()[DEFAULT_SCENE]


def unit_scene_path() -> str:
    """A gold GGX (alpha 0.1) sphere on a ground plane under the sun-and-sky map: the unit case."""
    return builtin_scenes()[UNIT_SCENE]


def scene_parameters(path: str) -> dict[str, str]:
    """The ``<default name=... value=...>`` parameters a scene file declares (top level)."""
    if not os.path.isfile(path):
        raise SceneError(f"scene file not found: {path}")
    try:
        root = ET.parse(path).getroot()
    except ET.ParseError as err:
        raise SceneError(f"cannot parse scene file {path}: {err}") from None
    return {el.get("name"): el.get("value") for el in root.findall("default")}


def scene_envmap(scene: mi.Scene) -> mi.Emitter | None:
    """The scene's ``envmap`` emitter, or None (no environment, or another infinite emitter)."""
    env = scene.environment()
    if env is None or "data" not in mi.traverse(env).keys():
        return None
    return env


def load_scene(path: str, envmap: str | None = None, mis_compensation: bool = False,
               res: int | None = None, spp: int | None = None, sampler: str | None = None,
               **params) -> mi.Scene:
    """Load a scene file, setting the parameters it declares.

    :param path: XML scene file.
    :param envmap: lat-long map replacing the scene's ``$envmap`` (None keeps its default).
    :param mis_compensation: value of ``$mis_compensation`` (ignored if the scene has no envmap
        parameter; requesting True for such a scene raises :class:`SceneError`).
    :param res: image width in pixels (``$res``; the height too, or ``$height`` at the scene's
        default aspect where the scene declares it), None keeps the default.
    :param spp: samples per pixel (``$spp``), None keeps the default.
    :param sampler: sampler plugin name (``$sampler``), None keeps the default.
    :param params: further ``$name`` parameters, passed as strings.
    :raises SceneError: missing file, or a requested parameter the scene does not declare.
    """
    declared = scene_parameters(path)
    wanted = dict(params)
    if envmap is not None:
        if not os.path.isfile(envmap):
            raise SceneError(f"environment map not found: {envmap}")
        wanted["envmap"] = os.path.abspath(envmap)
    if "mis_compensation" in declared:
        wanted["mis_compensation"] = "true" if mis_compensation else "false"
    elif mis_compensation:
        raise SceneError(f"{path} declares no $mis_compensation parameter")
    for name, value in (("res", res), ("spp", spp), ("sampler", sampler)):
        if value is not None:
            wanted[name] = value
    if res is not None and "height" in declared and "height" not in wanted:
        wanted["height"] = max(1, round(res * int(declared["height"]) / int(declared["res"])))
    undeclared = sorted(set(wanted) - set(declared))
    if undeclared:
        raise SceneError(f"{path} does not declare the parameter(s) {', '.join(undeclared)} "
                         f"(it declares: {', '.join(sorted(declared)) or 'none'})")
    # Loaded serially: in parallel, the objects' registry ids change from run to run, and
    # with them the order in which Dr.Jit traces the BSDFs' code, so each run's kernels
    # are new to Dr.Jit's kernel cache and compiled again (seconds of a first render).
    return mi.load_file(path, parallel=False, **{k: str(v) for k, v in wanted.items()})
