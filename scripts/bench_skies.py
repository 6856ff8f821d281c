"""Skies as users write them: ``sh_direct`` against Mitsuba's ``direct`` under a ``sunsky``
(three sun elevations) and a ``constant`` emitter, at equal time, and against the best of
Mitsuba's strategies (``direct`` with one emitter and one BSDF sample, with two emitter samples,
with two BSDF samples).

The built-in material-preview scene (Mitsuba's docs scene) with its ``envmap`` replaced by
the emitter. Per emitter: every method renders ``--passes`` passes of ``--spp`` samples
per pixel, interleaved (pass i of each method before pass i + 1 of any), after one untimed
render that builds, plans and compiles. Per method: the median pass time, the mean per-pixel
variance of the passes (luminance; variance over passes, so rare bright samples count), its
brightest pixel's variance, the efficiency 1 / (variance x time) and its ratio to
``direct``'s, and the mean's relative difference to ``direct``'s mean (a bias check at this
sample count, not a proof). ``sh_direct:product`` forces the product on every material
(what the plan chose against).

    python3 scripts/bench_skies.py [--res 240] [--spp 16] [--passes 16] [--json OUT.json]
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import sys
import time

import numpy as np

EMITTERS = {
    "sunsky_high": {"type": "sunsky", "hour": 12.0},
    "sunsky_mid": {"type": "sunsky", "hour": 16.5},
    "sunsky_low": {"type": "sunsky", "hour": 18.5},
    "constant": {"type": "constant", "radiance": {"type": "rgb", "value": [0.8, 0.9, 1.0]}},
}
METHODS = {"direct": {"type": "direct"},
           # Mitsuba's other strategies at the same two rays a sample: its emitter sampling alone
           # (what ``environment_only`` runs) and its BSDF sampling alone.
           "direct:emitter_only": {"type": "direct", "emitter_samples": 2, "bsdf_samples": 0},
           "direct:bsdf_only": {"type": "direct", "emitter_samples": 0, "bsdf_samples": 2},
           "sh_direct": {"type": "sh_direct"},
           "sh_direct:product": {"type": "sh_direct", "strategy": "product"}}
MITSUBA = [name for name in METHODS if name.split(":")[0] == "direct"]
"""Mitsuba's own strategies: ``vs best`` is a method's efficiency over the best of these."""


def load_scene_with(emitter: dict, res: int, spp: int):
    import mitsuba as mi

    from mitsuba_shsampling.scenes import builtin_scenes
    path = builtin_scenes()["material_preview"]
    with open(path) as f:
        xml = f.read()
    start = xml.index('<emitter type="envmap">')
    end = xml.index("</emitter>", start) + len("</emitter>")
    scene_dict_emitter = mi.load_dict(emitter)
    xml = xml[:start] + xml[end:]
    mi.Thread.thread().file_resolver().prepend(os.path.dirname(path))
    scene = mi.load_string(xml, res=str(res), spp=str(spp))
    # The scene without its envmap, then the emitter added: one dict of the loaded objects.
    parts = {"type": "scene", "sky": scene_dict_emitter}
    for i, shape in enumerate(scene.shapes()):
        parts[f"shape_{i}"] = shape
    parts["sensor"] = scene.sensors()[0]
    return mi.load_dict(parts)


def luminance(image: np.ndarray) -> np.ndarray:
    return image[..., :3] @ np.array([0.212671, 0.715160, 0.072169])


def measure(scene, passes: int, spp: int) -> dict:
    import mitsuba as mi
    integrators = {name: mi.load_dict(desc) for name, desc in METHODS.items()}
    for integrator in integrators.values():
        mi.render(scene, integrator=integrator, spp=spp, seed=0)  # build, plan, compile
    images = {name: [] for name in METHODS}
    times = {name: [] for name in METHODS}
    for i in range(passes):
        for name, integrator in integrators.items():
            start = time.perf_counter()
            image = np.array(mi.render(scene, integrator=integrator, spp=spp, seed=1 + i))
            times[name].append(time.perf_counter() - start)
            images[name].append(luminance(image))
    rows = {}
    reference = np.mean(images["direct"], axis=0).mean()
    for name in METHODS:
        stack = np.array(images[name])
        variance = stack.var(axis=0, ddof=1)
        pass_time = statistics.median(times[name])
        rows[name] = {"pass_s": pass_time, "variance": float(variance.mean()),
                      "max_pixel_variance": float(variance.max()),
                      "efficiency": 1.0 / (float(variance.mean()) * pass_time),
                      "mean_rel_diff": float(stack.mean() / reference - 1.0)}
    best = max(rows[name]["efficiency"] for name in MITSUBA)
    for name in METHODS:
        rows[name]["vs_direct"] = rows[name]["efficiency"] / rows["direct"]["efficiency"]
        rows[name]["vs_best_mitsuba"] = rows[name]["efficiency"] / best
    plan = integrators["sh_direct"].choice(scene)
    rows["sh_direct"]["plan"] = ({m.name: m.strategy.label for m in plan.materials} if plan is not None else None)
    return rows


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--res", type=int, default=240)
    parser.add_argument("--spp", type=int, default=16)
    parser.add_argument("--passes", type=int, default=16)
    parser.add_argument("--emitters", nargs="*", default=list(EMITTERS))
    parser.add_argument("--json")
    args = parser.parse_args(argv)

    import mitsuba as mi

    from mitsuba_shsampling.benchmarks import set_default_variant
    set_default_variant()
    import mitsuba_shsampling  # noqa: F401  (registers the plugins)
    results = {}
    print(f"{'emitter':<13} {'method':<18} {'pass (s)':>8} {'variance':>10} {'max px var':>10} "
          f"{'vs direct':>9} {'vs best':>8} {'mean diff':>9}")
    for name in args.emitters:
        scene = load_scene_with(EMITTERS[name], args.res, args.spp)
        results[name] = rows = measure(scene, args.passes, args.spp)
        for method, row in rows.items():
            print(f"{name:<13} {method:<18} {row['pass_s']:8.3f} {row['variance']:10.4g} "
                  f"{row['max_pixel_variance']:10.4g} {row['vs_direct']:9.2f} {row['vs_best_mitsuba']:8.2f} "
                  f"{row['mean_rel_diff']:+9.4f}")
        print(f"{'':13} plan: {rows['sh_direct']['plan']}")
    if args.json:
        with open(args.json, "w") as f:
            json.dump({"command": " ".join(["python3", "scripts/bench_skies.py"] + sys.argv[1:]),
                       "variant": mi.variant(), "res": args.res, "spp": args.spp, "passes": args.passes,
                       "results": results}, f, indent=1)
    return 0


if __name__ == "__main__":
    sys.exit(main())
