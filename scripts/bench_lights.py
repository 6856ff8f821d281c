"""An environment map plus the lights users add to it: ``sh_direct`` against Mitsuba's
``direct`` (with and without the envmap's ``mis_compensation``) at equal time.

A built-in scene under its map (``--envmap``), as it is (``map``), with a ``directional``
sun added (``sun``), and with two rectangular ``area`` lights added (``areas``). Per case:
every method renders ``--passes`` passes of ``--spp`` samples per pixel, interleaved
(pass i of each method before pass i + 1 of any), after one untimed render that builds,
plans and compiles. Per method: the median pass time and its ratio to ``direct``'s, the
mean per-pixel variance of the passes (luminance; over passes, so rare bright samples
count), the brightest pixel's variance, the efficiency 1 / (variance x time) and its
ratio to the best of Mitsuba's two, and the mean's relative difference to ``direct``'s
(a bias check at this sample count, not a proof). ``sh_direct:each`` and
``sh_direct:one`` are the two ``emitter_selection`` designs (the same estimator where
the map is the only emitter), ``sh_direct:auto`` the plan's pick between them (the default;
the JSON gives what it weighed). The last column divides a case's ratio by the ``map``
case's: how much of the map-only gain the added lights leave. With ``--family path``
the methods are ``path`` (with and without ``mis_compensation``) and ``sh_path`` at
``--max-depth`` (the columns named after ``direct`` then mean ``path``).

    python3 scripts/bench_lights.py [--scene material_preview] [--res 320] [--spp 16]
                                    [--passes 16] [--envmap FILE] [--family direct|path]
                                    [--max-depth 3] [--json OUT.json]
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import time

import numpy as np

from bench_skies import luminance


def extra_lights(case: str) -> dict:
    """The emitters ``case`` adds to the scene (Mitsuba dicts by name)."""
    import mitsuba as mi
    T = mi.ScalarTransform4f

    def rectangle(origin, radiance):
        return {"type": "rectangle",
                "to_world": T().look_at(origin=origin, target=[0, 0.5, 0], up=[0, 1, 0]) @ T().scale(0.35),
                "emitter": {"type": "area", "radiance": {"type": "rgb", "value": radiance}}}

    if case == "map":
        return {}
    if case == "sun":
        return {"sun": {"type": "directional", "direction": [-0.45, -0.75, -0.5],
                        "irradiance": {"type": "rgb", "value": [3.0, 2.8, 2.5]}}}
    if case == "areas":
        return {"key_light": rectangle([2.2, 2.8, 2.0], [9.0, 8.5, 8.0]),
                "fill_light": rectangle([-2.6, 1.6, 1.4], [3.0, 3.2, 3.6])}
    raise ValueError(f"unknown case {case!r}")


CASES = ("map", "sun", "areas")
MITSUBA = ("direct", "direct_misc")


def methods(args) -> dict:
    """Method name -> integrator dict; the first two are Mitsuba's (:data:`MITSUBA`'s names,
    ``direct_misc`` rendered on the compensated map)."""
    if args.family == "path":
        path = {"type": "path", "max_depth": args.max_depth}
        return {"direct": path, "direct_misc": path, "sh_path": {"type": "sh_path", "max_depth": args.max_depth}}
    return {"direct": {"type": "direct"}, "direct_misc": {"type": "direct"},
            "sh_direct:each": {"type": "sh_direct", "emitter_selection": "each"},
            "sh_direct:one": {"type": "sh_direct", "emitter_selection": "one"},
            "sh_direct:auto": {"type": "sh_direct"}}


def scene_with(args, case: str, mis_compensation: bool):
    """The built-in scene with ``case``'s lights added."""
    import mitsuba as mi

    from mitsuba_shsampling.scenes import builtin_scenes, load_scene
    scene = load_scene(builtin_scenes()[args.scene], envmap=args.envmap, mis_compensation=mis_compensation,
                       res=args.res, spp=args.spp)
    parts = {"type": "scene", "sensor": scene.sensors()[0], "environment": scene.environment()}
    parts.update({f"shape_{i}": shape for i, shape in enumerate(scene.shapes())})
    parts.update(extra_lights(case))
    return mi.load_dict(parts)


def measure(args, case: str) -> dict:
    """Interleaved passes of every method on ``case``; a row per method."""
    import mitsuba as mi
    scenes = {False: scene_with(args, case, False), True: scene_with(args, case, True)}
    runs = {name: (scenes[name == "direct_misc"], mi.load_dict(desc)) for name, desc in methods(args).items()}
    for scene, integrator in runs.values():
        mi.render(scene, integrator=integrator, spp=args.spp, seed=0)  # build, plan, compile
    images = {name: [] for name in runs}
    times = {name: [] for name in runs}
    for i in range(args.passes):
        for name, (scene, integrator) in runs.items():
            start = time.perf_counter()
            image = np.array(mi.render(scene, integrator=integrator, spp=args.spp, seed=1 + i))
            times[name].append(time.perf_counter() - start)
            images[name].append(luminance(image))
    rows, reference = {}, np.mean(images["direct"], axis=0).mean()
    for name in runs:
        stack = np.array(images[name])
        variance = stack.var(axis=0, ddof=1)
        rows[name] = {"pass_s": statistics.median(times[name]), "variance": float(variance.mean()),
                      "max_pixel_variance": float(variance.max()),
                      "mean_rel_diff": float(stack.mean() / reference - 1.0)}
        rows[name]["efficiency"] = 1.0 / (rows[name]["variance"] * rows[name]["pass_s"])
    best = max(rows[name]["efficiency"] for name in MITSUBA)
    for name, row in rows.items():
        row["vs_best_mitsuba"] = row["efficiency"] / best
        row["time_vs_direct"] = row["pass_s"] / rows["direct"]["pass_s"]
    for name in [n for n in runs if n.startswith("sh_")]:
        plan = runs[name][1].choice(scenes[False])
        rows[name]["plan"] = {m.name: m.strategy.label for m in plan.materials} if plan else None
        if plan is not None and plan.emitter_selection:
            rows[name]["emitter_selection"] = plan.emitter_selection
    return rows


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--scene", default="material_preview")
    parser.add_argument("--res", type=int, default=320)
    parser.add_argument("--spp", type=int, default=16)
    parser.add_argument("--passes", type=int, default=16)
    parser.add_argument("--envmap", help="lat-long map (default: the scene's own)")
    parser.add_argument("--cases", nargs="*", default=list(CASES), choices=CASES)
    parser.add_argument("--family", choices=("direct", "path"), default="direct")
    parser.add_argument("--max-depth", type=int, default=3)
    parser.add_argument("--json")
    args = parser.parse_args(argv)

    import mitsuba as mi

    from mitsuba_shsampling.benchmarks import set_default_variant
    set_default_variant()
    import mitsuba_shsampling  # noqa: F401  (registers the plugins)
    results = {}
    print(f"{'case':<6} {'method':<15} {'pass (s)':>8} {'vs direct':>9} {'variance':>10} {'max px var':>10} "
          f"{'vs best':>7} {'of map':>6} {'mean diff':>9}")
    for case in args.cases:
        results[case] = rows = measure(args, case)
        for method, row in rows.items():
            of_map = (f"{row['vs_best_mitsuba'] / results['map'][method]['vs_best_mitsuba']:6.2f}"
                      if "map" in results and case != "map" else "")
            print(f"{case:<6} {method:<15} {row['pass_s']:8.3f} {row['time_vs_direct']:9.2f} {row['variance']:10.4g} "
                  f"{row['max_pixel_variance']:10.4g} {row['vs_best_mitsuba']:7.2f} {of_map:>6} "
                  f"{row['mean_rel_diff']:+9.4f}")
        for method in [m for m in rows if m.startswith("sh_")]:
            print(f"{'':6} {method}'s plan: {rows[method]['plan']}")
    if args.json:
        with open(args.json, "w") as f:
            json.dump({"command": " ".join(["python3", "scripts/bench_lights.py"] + sys.argv[1:]),
                       "variant": mi.variant(), "args": vars(args), "results": results}, f, indent=1)
    return 0


if __name__ == "__main__":
    sys.exit(main())
