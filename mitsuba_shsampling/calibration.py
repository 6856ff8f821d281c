"""The ``calibrate`` command: this machine's cost model of the environment strategies.

    python -m mitsuba_shsampling calibrate [--runs 3] [--res 320] [--variant llvm_ad_rgb]

Times the pilot passes of the built-in material studio (every strategy on every
material that can run it, the lean kernel, interleaved; :mod:`~.integrators.pilots`)
with ``sh_direct`` and with ``sh_path``, turns them into a
:class:`~.integrators.costs.CostModel` each, and keeps them in the cache folder
(:func:`~.integrators.costs.calibration_path`), where ``plan`` ``estimate`` finds
them. Without a calibration the plugins plan from the shipped model. With
``--runs`` N each figure is the median of N runs. ``--print-only`` leaves the
calibration file alone (e.g. to update the shipped model).
"""

from __future__ import annotations

import argparse
import dataclasses
import statistics
import time

from .integrators.costs import set_calibrator

CALIBRATION_SCENE = "material_studio"
"""The built-in scene the calibration times: ten materials (glossy, diffuse, textured,
wrapped, a glass block), a 115k-triangle mesh, a Gaussian film filter."""

CALIBRATION_RES = 320
"""Its width in pixels: pilot passes of 2^17 camera samples at one spp."""

PLUGINS = {"direct": "sh_direct", "path": "sh_path"}
"""Cost-model kind -> the plugin it is timed with (at its default options)."""


def add_parser(subparsers, variant_default: str) -> argparse.ArgumentParser:
    parser = subparsers.add_parser("calibrate", help="time the strategies once on this machine (the plan's cost model)")
    parser.add_argument("--variant", default=variant_default, help="Mitsuba JIT variant (default %(default)s)")
    parser.add_argument("--runs", type=int, default=1, help="runs whose median is kept (default %(default)s)")
    parser.add_argument("--res", type=int, default=CALIBRATION_RES, help="film width (default %(default)s)")
    parser.add_argument("--print-only", action="store_true", help="print the model, do not keep it")
    return parser


def measure_model(kind: str, res: int):
    """One timed run of ``kind``'s plugin on the calibration scene: its :class:`CostModel`."""
    import drjit as dr
    import mitsuba as mi

    from .integrators.chooser import pilot_candidates, pilot_shares, predict
    from .integrators.costs import CostModel
    from .integrators.pilots import PILOT_LANES, measure_pass_costs
    from .integrators.strategy import CARRYING_MITSUBA_STRATEGIES
    from .scenes import builtin_scenes, load_scene

    scene = load_scene(builtin_scenes()[CALIBRATION_SCENE], res=res)
    sensor = scene.sensors()[0]
    integrator = mi.load_dict({"type": PLUGINS[kind]})
    env = integrator.scenes.get(scene)
    p = predict(env, sensor, 1, 1, {})
    # Every pilot, those of the strategies that carry every sample too: the calibration prices every strategy.
    candidates = pilot_candidates(env, p, {}, timed=True, alone=CARRYING_MITSUBA_STRATEGIES)
    film = sensor.film().crop_size()
    spp = max(1, -(-PILOT_LANES // (int(film[0]) * int(film[1]))))

    def render_pass(seed: int):
        image = mi.SamplingIntegrator.render(integrator, scene, sensor, seed, spp)
        dr.eval(image)
        dr.sync_thread()
        return None  # images are not needed: only the times

    # Mitsuba's render dispatches to the plugin's own, which would plan: it must render as set.
    integrator.chooser.piloting = True
    try:
        pilots = measure_pass_costs(env, candidates, render_pass, spp=spp)
    finally:
        integrator.chooser.piloting = False
    return CostModel.from_pass_times(pilots.pass_time, pilot_shares(env, p), "calibration")


def calibrate(runs: int = 1, res: int = CALIBRATION_RES) -> tuple[dict, float]:
    """Kind -> the median :class:`CostModel` of ``runs`` runs, and the seconds it took."""
    from .integrators.costs import CostModel

    start = time.perf_counter()
    models = {}
    for kind in PLUGINS:
        measured = [measure_model(kind, res) for _ in range(runs)]
        fields = [f.name for f in dataclasses.fields(CostModel) if f.name != "source"]
        models[kind] = CostModel(**{f: statistics.median(getattr(m, f) for m in measured) for f in fields},
                                 source="calibration")
    return models, time.perf_counter() - start


# A plan on a backend without shipped figures calibrates the machine through this (late bound:
# tests replace `calibrate`).
set_calibrator(lambda: calibrate())


def main(args, set_variant) -> int:
    """The ``calibrate`` command; ``set_variant(name)`` sets the variant or says why not
    (:func:`~mitsuba_shsampling.command_line.set_variant`, passed in by the CLI, which sits above)."""
    set_variant(args.variant)
    from .integrators import register
    from .integrators.costs import save_calibration

    register()

    models, seconds = calibrate(max(1, args.runs), args.res)
    fields = [f.name for f in dataclasses.fields(type(models["direct"])) if f.name != "source"]
    print(f"{'figure (lean passes)':<22}" + "".join(f"{kind:>10}" for kind in models))
    for f in fields:
        print(f"{f:<22}" + "".join(f"{getattr(m, f):>10.3f}" for m in models.values()))
    print(f"calibration took {seconds:.1f} s")
    if not args.print_only:
        print(f"wrote {save_calibration(models, seconds, args.variant)}")
    return 0
