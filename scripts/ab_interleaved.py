"""A/B of integrator settings on one scene, timed interleaved, in one process.

Pass k of every integrator runs before pass k + 1 of any (same seeds for all),
so a slow spell of the machine falls on all of them alike; round k starts with
integrator k (mod their number), so no integrator always follows the same one; with
``--instances K`` each integrator is loaded K times and round k uses instance k mod K,
which averages out the speed of a single instance. Prints, against the first
integrator: the per-pixel luminance variance across passes (the expected squared
error of one pass, tails included), the median pass time and the efficiency
1 / (variance x time), and for each integrator its slowest instance's median
pass time over its fastest's; ``--json`` writes the same.

    python scripts/ab_interleaved.py SCENE.xml --envmap MAP --res 192 --spp 4 --passes 16 \\
        '{"type": "direct"}' '{"type": "sh_direct"}' '{"type": "sh_direct", "strategy": "product_only"}'

A ``path_settings`` entry sets fields of a path plugin's loop settings that are no plugin
parameter (``integrators/path_loop.py``: ``PathSettings``), e.g.
``'{"type": "sh_path", "path_settings": {"through_dirac": false}}'``.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import time

import numpy as np

import mitsuba_shsampling  # noqa: F401  (points Dr.Jit at a usable libLLVM first)
import mitsuba as mi

from mitsuba_shsampling.frozen import FrozenPass

LUMINANCE = np.array([0.2126, 0.7152, 0.0722])


def load_integrator(description: dict):
    """``mi.load_dict(description)``, its ``path_settings`` (if any) set on the loop settings."""
    description = dict(description)
    settings = description.pop("path_settings", None)
    integrator = mi.load_dict(description)
    if settings:
        integrator.settings = dataclasses.replace(integrator.settings, **settings)
    return integrator


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("scene")
    parser.add_argument("integrators", nargs="+", help="integrator dicts as JSON")
    parser.add_argument("--envmap", default=None)
    parser.add_argument("--res", type=int, default=192)
    parser.add_argument("--spp", type=int, default=4)
    parser.add_argument("--passes", type=int, default=16)
    parser.add_argument("--json", default=None)
    parser.add_argument("--no-freeze", action="store_true", help="time traced passes (tracing included)")
    parser.add_argument("--instances", type=int, default=1,
                        help="load each integrator this many times and use them in turn (averages out "
                             "an instance's own speed)")
    parser.add_argument("--fixed-order", action="store_true",
                        help="run every round in the listed order (default: round k starts with integrator k)")
    args = parser.parse_args()
    if args.instances < 1:
        parser.error(f"--instances must be >= 1, got {args.instances}")

    mi.set_variant("llvm_ad_rgb")
    mitsuba_shsampling.register()
    from mitsuba_shsampling.scenes import load_scene

    scene = load_scene(args.scene, envmap=args.envmap, res=args.res)
    # Each integrator is loaded --instances times: one instance of a configuration can run
    # ~10 % slower than another for a whole run (docs/MEASUREMENTS.md, "Timing: each
    # integrator instance has its own speed"); round k uses instance k mod K of every one.
    integrators = {text: [load_integrator(json.loads(text)) for _ in range(args.instances)]
                   for text in args.integrators}
    for instances in integrators.values():  # compile outside the timed passes
        for integrator in instances:
            np.array(mi.render(scene, integrator=integrator, spp=args.spp, seed=10_000))
    # Then record each pass once (as compare does) unless --no-freeze: timed passes replay it.
    passes = {name: [FrozenPass(scene, scene.sensors()[0], integrator, args.spp, enabled=not args.no_freeze)
                     for integrator in instances] for name, instances in integrators.items()}
    for frozen in (f for instances in passes.values() for f in instances):
        np.array(frozen(10_001))
    times = {name: [] for name in integrators}
    images = {name: [] for name in integrators}
    names = list(integrators)
    for k in range(args.passes):
        # Round k starts with integrator k (mod their number) unless --fixed-order: a pass
        # may leave the caches or the clock in a state that favours or slows whichever
        # integrator comes next, and a fixed order would give that to one of them every time.
        shift = 0 if args.fixed_order else k % len(names)
        for name in names[shift:] + names[:shift]:
            start = time.perf_counter()
            image = np.array(passes[name][k % args.instances](k))
            times[name].append(time.perf_counter() - start)
            images[name].append(image[..., :3] @ LUMINANCE)

    rows = []
    for name in integrators:
        variance = float(np.stack(images[name]).var(axis=0, ddof=1).mean())
        rows.append({"integrator": json.loads(name), "pixel_variance": variance,
                     "time_s": float(np.median(times[name])), "pass_times_s": times[name]})
    base = rows[0]
    print(f"{'integrator':72s} {'var':>7s} {'time':>7s} {'eff':>7s} {'time p10-p90':>13s} {'inst.':>6s}"
          "   (relative to the first; inst.: slowest over fastest instance's median time)")
    for name, row in zip(integrators, rows):
        row["variance_ratio"] = row["pixel_variance"] / base["pixel_variance"]
        row["time_ratio"] = row["time_s"] / base["time_s"]
        row["efficiency_ratio"] = 1.0 / (row["variance_ratio"] * row["time_ratio"])
        # The spread of the time ratio: pass k against the first integrator's pass k,
        # timed next to it (the machine's load drifts between passes, not within a pair).
        paired = np.array(row["pass_times_s"]) / np.array(base["pass_times_s"])
        row["paired_time_ratio_p10"], row["paired_time_ratio_p90"] = (float(q) for q in np.quantile(paired, [0.1, 0.9]))
        # Each instance's median pass time over the integrator's: how much one instance alone would have moved it.
        per_instance = [float(np.median(row["pass_times_s"][i::args.instances])) for i in range(args.instances)]
        row["instance_time_spread"] = max(per_instance) / min(per_instance)
        spread = f"{row['paired_time_ratio_p10']:.3f}-{row['paired_time_ratio_p90']:.3f}"
        print(f"{name:72s} {row['variance_ratio']:7.3f} {row['time_ratio']:7.3f} {row['efficiency_ratio']:7.3f} {spread:>13s} "
              f"{row['instance_time_spread']:6.3f}")
    if args.json:
        with open(args.json, "w") as f:
            json.dump({"scene": args.scene, "envmap": args.envmap, "res": args.res, "spp": args.spp,
                       "passes": args.passes, "instances": args.instances,
                       "frozen": {name: all(p.frozen for p in instances) for name, instances in passes.items()},
                       "rows": rows}, f, indent=2)


if __name__ == "__main__":
    main()
