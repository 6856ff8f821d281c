"""``render``: what the ``mitsuba`` executable does, with this package's plugins registered.

The ``mitsuba`` command-line renderer is a C++ program: it cannot load Python
plugins, so ``<integrator type="sh_path"/>`` fails there with "Plugin not
found". This command is its drop-in::

    python -m mitsuba_shsampling render SCENE.xml --integrator sh_path:max_depth=8 --spp 256 \\
        -o out.exr -D envmap=my_map.exr -D res=512 [--variant llvm_ad_rgb]

``SCENE`` is an XML file or the name of a built-in scene (see
:func:`mitsuba_shsampling.scenes.builtin_scenes`). ``-D name=value`` sets a
scene's ``$name`` parameter, as for ``mitsuba``. ``--integrator TYPE[:NAME=VALUE,...]``
replaces the scene's integrator by a plugin of that type with those parameters
(:func:`parse_integrator`; the others at their defaults); ``--envmap FILE``
replaces the scene's ``envmap`` emitter by one of that map, as ``compare
--envmap`` does (:func:`.report.scene_setup.with_environment`); ``--spp``
overrides the sensor's sample count. The image is rendered in passes with consecutive seeds
(``--seed``, ``--seed + 1``, ...), shown by a progress bar, and their
spp-weighted mean is written: the same estimate as one render with all the
samples (for independent samplers; stratified ones stratify within a pass).
The output format follows the extension: ``.exr`` (default, float32, the
film's channels), ``.hdr``, ``.pfm``, or ``.png``/``.jpg`` (sRGB, 8 bit); the
extension and the output folder are checked before rendering, so that a render
is never lost to a path it cannot be written to.
"""

from __future__ import annotations

import argparse
import math
import os
import re
import sys
import time

#: Largest number of samples per pixel rendered in one pass (one progress step).
PASS_SPP = 16
#: Image formats ``render`` writes, by extension; the 8-bit ones are written in sRGB.
OUTPUT_FORMATS = (".exr", ".hdr", ".pfm", ".png", ".jpg", ".jpeg")
LDR_FORMATS = (".png", ".jpg", ".jpeg")


class RenderError(ValueError):
    """Bad ``render`` input (malformed ``-D``, impossible pass split, a scene that
    does not load or has no sensor); the message is one line."""


def add_parser(subparsers, variant_default: str) -> argparse.ArgumentParser:
    """Add the ``render`` subcommand to a ``cli`` subparsers object."""
    parser = subparsers.add_parser(
        "render", help="render a scene to an image, like the mitsuba executable (which cannot "
                       "load Python plugins)")
    parser.add_argument("scene", metavar="SCENE", help="scene file (.xml) or built-in scene name")
    parser.add_argument("-o", "--output", help="image file (default: SCENE's stem + .exr, here)")
    parser.add_argument("-D", dest="defines", action="append", default=[], metavar="NAME=VALUE",
                        help="set the scene parameter $NAME (repeatable), as mitsuba -D")
    parser.add_argument("--integrator", metavar="TYPE[:NAME=VALUE,...]",
                        help="integrator replacing the scene's, with its parameters, e.g. "
                             "sh_path:max_depth=8,strategy=product (values: integer, else float, "
                             "else true/false, else text)")
    parser.add_argument("--envmap", metavar="FILE", help="lat-long map replacing the scene's envmap emitter")
    parser.add_argument("--spp", type=int, help="samples per pixel, >= 1 (default: the scene's sampler)")
    parser.add_argument("--passes", type=int,
                        help=f"render passes (default: enough for at most {PASS_SPP} spp each)")
    parser.add_argument("--seed", type=int, default=0, help="seed of the first pass (default %(default)s)")
    parser.add_argument("-m", "--variant", default=variant_default,
                        help="Mitsuba JIT variant (default %(default)s)")
    parser.add_argument("--no-progress", action="store_true", help="hide the progress bar")
    return parser


def parse_defines(items: list[str]) -> dict[str, str]:
    """``["name=value", ...]`` -> ``{name: value}``; RenderError naming a malformed item."""
    defines = {}
    for item in items:
        name, sep, value = item.partition("=")
        if not sep or not name.strip():
            raise RenderError(f"-D expects NAME=VALUE, got '{item}'")
        defines[name.strip()] = value
    return defines


def plugin_value(text: str) -> int | float | bool | str:
    """A plugin parameter's value from text, by the first reading that fits: an integer, a
    float, ``true``/``false`` (any case), else the text itself. The plugins check exact types
    (an integer parameter refuses ``8.0``), so ``8`` must stay an integer."""
    for read in (int, float):
        try:
            return read(text)
        except ValueError:
            pass
    if text.strip().lower() in ("true", "false"):
        return text.strip().lower() == "true"
    return text


def parse_integrator(spec: str) -> dict:
    """``TYPE[:NAME=VALUE,...]`` -> its ``mi.load_dict`` description, each value read by
    :func:`plugin_value`: ``sh_path:max_depth=8,strategy=product`` ->
    ``{"type": "sh_path", "max_depth": 8, "strategy": "product"}``. A value cannot hold a comma.
    RenderError naming a malformed or repeated parameter."""
    plugin, _, params = spec.partition(":")
    desc = {"type": plugin.strip()}
    if not desc["type"]:
        raise RenderError(f"--integrator expects TYPE[:NAME=VALUE,...], got '{spec}'")
    for item in params.split(",") if params.strip() else []:
        name, sep, value = item.partition("=")
        name = name.strip()
        if not sep or not name:
            raise RenderError(f"--integrator parameters are NAME=VALUE, separated by commas, got '{item}' "
                              f"in '{spec}'")
        if name in desc:
            raise RenderError(f"--integrator sets '{name}' twice in '{spec}'")
        desc[name] = plugin_value(value.strip())
    return desc


def pass_plan(spp: int, passes: int | None = None) -> list[int]:
    """Samples per pixel of each pass: ``passes`` passes (default: ceil(spp /
    :data:`PASS_SPP`)) whose counts differ by at most one and sum to ``spp``."""
    if spp < 1:
        raise RenderError(f"--spp must be >= 1, got {spp}")
    passes = math.ceil(spp / PASS_SPP) if passes is None else passes
    if not 1 <= passes <= spp:
        raise RenderError(f"--passes must be in [1, spp = {spp}], got {passes}")
    return [spp // passes + (1 if k < spp % passes else 0) for k in range(passes)]


def resolve_scene(scene: str) -> str:
    """Path of ``scene``: an existing file, or a built-in scene's name."""
    from .scenes import SceneError, builtin_scenes

    if os.path.isfile(scene):
        return scene
    builtin = builtin_scenes()
    if scene in builtin:
        return builtin[scene]
    raise SceneError(f"scene file not found: {scene} (nor a built-in scene: {', '.join(builtin)})")


def write_image(path: str, image, film) -> None:
    """Write ``image`` (H, W, C), with the channel layout of ``film``'s developed
    bitmap when it has C channels (names such as ``R, G, B, A`` or AOVs)."""
    import mitsuba as mi
    import numpy as np

    image = np.ascontiguousarray(image, dtype=np.float32)
    layout = film.bitmap()
    names = [field.name for field in layout.struct_()]
    if len(names) == image.shape[2]:
        bitmap = mi.Bitmap(image, layout.pixel_format(), names)
    else:
        bitmap = mi.Bitmap(image)
    if os.path.splitext(path)[1].lower() in LDR_FORMATS:
        rgb = mi.Bitmap.PixelFormat.RGBA if bitmap.has_alpha() else mi.Bitmap.PixelFormat.RGB
        bitmap = bitmap.convert(rgb, mi.Struct.Type.UInt8, srgb_gamma=True)
    bitmap.write(path)


def check_output(path: str) -> None:
    """RenderError unless an image can be written to ``path``: a format of
    :data:`OUTPUT_FORMATS` and an existing, writable folder."""
    extension = os.path.splitext(path)[1].lower()
    if extension not in OUTPUT_FORMATS:
        raise RenderError(f"cannot write '{path}': the output format follows the extension, one of "
                          f"{', '.join(OUTPUT_FORMATS)}")
    folder = os.path.dirname(os.path.abspath(path))
    if not os.path.isdir(folder):
        raise RenderError(f"cannot write '{path}': the folder {folder} does not exist")
    if not os.access(folder, os.W_OK) or os.path.isdir(path):
        raise RenderError(f"cannot write '{path}': not a writable file path")


def render_file(args) -> dict:
    """Load, render and write as ``args`` say (a variant must be set); returns a summary."""
    import mitsuba as mi
    import numpy as np
    from tqdm import tqdm

    from .frozen import FrozenPass
    from .integrators.chooser import compiling_note
    from .report.scene_setup import with_environment

    path = resolve_scene(args.scene)
    defines = parse_defines(args.defines)
    plugin = parse_integrator(args.integrator) if args.integrator else None
    if args.envmap and not os.path.isfile(args.envmap):
        raise RenderError(f"environment map not found: {args.envmap}")
    output = args.output or os.path.splitext(os.path.basename(path))[0] + ".exr"
    check_output(output)
    try:
        scene = mi.load_file(path, parallel=False, **defines)  # stable registry ids: see scenes.load_scene
    except RuntimeError as err:
        raise RenderError(f"cannot load {path}: {_one_line(err)}") from None
    if args.envmap:
        scene = with_environment(scene, args.envmap)
    integrator = load_integrator(plugin) if plugin else scene.integrator()
    if not scene.sensors():
        raise RenderError(f"{path} has no sensor to render from")
    if integrator is None:
        raise RenderError(f"{path} has no integrator; choose one with --integrator")
    sensor = scene.sensors()[0]
    spp = sensor.sampler().sample_count() if args.spp is None else args.spp
    plan = pass_plan(spp, args.passes)

    start = time.perf_counter()
    # The project's integrators plan before the first pass; the plan is shown before the
    # passes run (Mitsuba's integrators have none).
    strategy = integrator.plan(scene, sensor) if hasattr(integrator, "plan") else None
    setup_s = time.perf_counter() - start
    if strategy is not None:
        print(f"plan ({strategy.mode}, set-up {setup_s:.2f} s{compiling_note(strategy.kernels_compiled)}): "
              f"{strategy.summary()}", flush=True)
    total = None
    with tqdm(total=spp, unit="spp", desc=os.path.basename(path), disable=args.no_progress,
              file=sys.stderr) as bar:
        frozen = {}
        for k, pass_spp in enumerate(plan):
            if k == 0 or len(plan) < 3:  # the first pass compiles; few passes are not worth a recording
                image = mi.render(scene, sensor=sensor, integrator=integrator, spp=pass_spp, seed=args.seed + k)
            else:  # later ones replay a recording of one pass (no re-tracing: see frozen.py)
                if pass_spp not in frozen:
                    frozen[pass_spp] = FrozenPass(scene, sensor, integrator, pass_spp)
                image = frozen[pass_spp](args.seed + k)
            image = np.array(image, dtype=np.float64)
            total = pass_spp * image if total is None else total + pass_spp * image
            bar.update(pass_spp)
    elapsed = time.perf_counter() - start
    image = total / spp
    write_image(output, image, sensor.film())
    return {"output": os.path.abspath(output), "shape": image.shape, "spp": spp,
            "passes": len(plan), "time_s": elapsed, "setup_s": setup_s,
            "plan": strategy.summary() if strategy is not None else None}


def load_integrator(desc: dict):
    """The integrator of ``desc`` (:func:`parse_integrator`); RenderError naming the plugin
    when it is unknown, refuses its parameters or is no integrator."""
    import mitsuba as mi

    try:
        integrator = mi.load_dict(desc)
    except RuntimeError as err:
        raise RenderError(f"cannot load the integrator '{desc['type']}': {_one_line(err)}") from None
    if not isinstance(integrator, mi.Integrator):
        raise RenderError(f"'{desc['type']}' is a {type(integrator).__name__} plugin, not an integrator")
    return integrator


def _one_line(err: BaseException) -> str:
    """A Mitsuba parser error in one line: without the ``[file.cpp:123]`` source
    tags, and for a Python plugin's exception (which arrives as text with its
    traceback) only the exception's own last line."""
    text = str(err)
    head, traceback, tail = text.partition("Traceback (most recent call last):")
    if traceback:
        text = head + " " + tail.strip().splitlines()[-1]
    return " ".join(re.sub(r"\[[\w.]+:\d+\] ?", "", text).split()) or type(err).__name__


def main(args, set_variant) -> int:
    """Run the ``render`` subcommand; ``set_variant`` is the CLI's checked ``mi.set_variant``."""
    set_variant(args.variant)
    summary = render_file(args)
    height, width = summary["shape"][:2]
    print(f"wrote {summary['output']} ({width}x{height}, {summary['shape'][2]} channels, "
          f"{summary['spp']} spp in {summary['passes']} pass(es), {summary['time_s']:.1f} s "
          f"of which set-up {summary['setup_s']:.1f} s)")
    return 0
