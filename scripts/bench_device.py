"""The device benchmark (issue 47): this package's integrators against Mitsuba's on one JIT
variant (default ``cuda_ad_rgb``), on the realistic scenes at 1280 px, at equal time.

Per scene and map, three groups, each rendered ``--passes`` times, interleaved with the
methods' order rotated from pass to pass (``report.rendering.interleaved_passes``, after an
untimed render that plans and compiles), with ``mi.render`` as a user calls it (``--freeze``
replays recorded passes instead, where each method can be recorded; Mitsuba's ``path`` and
``prb`` cannot always, and would then be timed with their tracing against frozen rivals):

- direct lighting: ``direct`` and ``direct`` + ``mis_compensation`` (Mitsuba's) against
  ``sh_direct`` (its plan) and ``sh_direct`` ``strategy`` ``environment`` (Mitsuba's
  estimator, run by this package's Python loop);
- paths at ``--path-depth``: ``path`` and ``path`` + ``mis_compensation`` against ``sh_path``
  (plan) and ``sh_path`` ``strategy`` ``environment``;
- differentiable paths at ``--prb-depth`` (primal passes): ``prb`` and ``prb`` +
  ``mis_compensation`` against ``sh_prb``.

Each of this package's rows gives, against the group's best Mitsuba method at equal time
(the best 1 / (variance x pass time)): the variance ratio, the pass-time ratio, the
efficiency ratio, the image mean's relative difference (a bias check at this sample
count), and the set-up seconds (state and plan). Variance: the per-pixel variance of the
passes' luminance, averaged over the film. The environment-strategy rows run the same
estimator as Mitsuba's compensated methods, so their pass-time ratio is the cost of the
Python loop on this backend (issue 47's bar: <= 1.05).

    python3 scripts/bench_device.py [--variant cuda_ad_rgb] [--res 1280] [--spp 64] [--passes 8]
        [--scenes material_studio interior] [--maps scene tests/data/envmaps/forest_slope_1k.hdr]
        [--groups direct path prb] [--freeze] [--json OUT.json]

How to run it on a device machine: docs/USAGE.md, "On a GPU".
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
import time

import numpy as np

LUMINANCE = np.array([0.212671, 0.715160, 0.072169])

GROUPS = ("direct", "path", "prb")


def group_methods(group: str) -> dict:
    """Method name -> :class:`~mitsuba_shsampling.report.methods.Method` of ``group``;
    Mitsuba's first (role ``mitsuba``), then this package's."""
    from mitsuba_shsampling.report.methods import METHODS, MULTI_BOUNCE, PROJECT, Method

    known = {m.name: m for m in METHODS}
    compensated = {"mis_compensation": True}
    if group == "direct":
        ours = known["sh_direct"]
        return {"direct": known["direct"], "direct_misc": known["direct_misc"], "sh_direct": ours,
                "sh_direct:environment": dataclasses.replace(
                    ours, name="sh_direct:environment", integrator={**ours.integrator, "strategy": "environment"})}
    if group == "path":
        ours = known["sh_path"]
        return {"path": known["path"],
                "path_misc": dataclasses.replace(known["path"], name="path_misc", scene_params=compensated),
                "sh_path": ours,
                "sh_path:environment": dataclasses.replace(
                    ours, name="sh_path:environment", integrator={**ours.integrator, "strategy": "environment"})}
    if group == "prb":
        prb = Method("prb", "Mitsuba's prb (primal)", {"type": "prb"}, family=MULTI_BOUNCE)
        return {"prb": prb, "prb_misc": dataclasses.replace(prb, name="prb_misc", scene_params=compensated),
                "sh_prb": Method("sh_prb", "SH prb (primal)", {"type": "sh_prb"}, family=MULTI_BOUNCE,
                                 plugin="sh_prb", product_sampling=True, role=PROJECT)}
    raise ValueError(f"unknown group {group!r}")


def group_rows(methods: dict, passes: dict, renderers: dict) -> dict:
    """Per method of the group: variance, pass time, efficiency, image mean; and for this
    package's methods their ratios to the group's best Mitsuba method."""
    from mitsuba_shsampling.report.methods import MITSUBA

    rows = {}
    for name, pass_set in passes.items():
        luminance = pass_set.images[..., :3] @ LUMINANCE
        variance = float(luminance.var(axis=0, ddof=1).mean())
        rows[name] = {"variance": variance, "pass_s": pass_set.time_s, "mean": float(luminance.mean()),
                      "efficiency": 1.0 / (variance * pass_set.time_s) if variance > 0 else float("inf"),
                      "setup_s": renderers[name].setup_time_s}
    mitsuba = [n for n in rows if methods[n].role == MITSUBA]
    if not mitsuba:
        return rows
    best = max(mitsuba, key=lambda n: rows[n]["efficiency"])
    for name, row in rows.items():
        if methods[name].role != MITSUBA:
            reference = rows[best]
            row.update(against=best, variance_ratio=row["variance"] / reference["variance"],
                       time_ratio=row["pass_s"] / reference["pass_s"],
                       efficiency_ratio=row["efficiency"] / reference["efficiency"],
                       mean_rel_diff=row["mean"] / reference["mean"] - 1.0)
    return rows


def measure_cell(scene_path: str, envmap: str | None, args) -> dict:
    """Every group on one scene and map: group -> rows."""
    from mitsuba_shsampling.report.rendering import MethodRenderer, interleaved_passes

    result = {}
    for group in args.groups:
        depth = {"direct": 2, "path": args.path_depth, "prb": args.prb_depth}[group]
        settings = {"res": args.res, "sampler": "independent", "envmap": envmap, "max_depth": depth,
                    "freeze": args.freeze}
        methods = group_methods(group)
        renderers = {name: MethodRenderer(scene_path, method, settings) for name, method in methods.items()}
        passes, failed = interleaved_passes({n: (r, args.spp) for n, r in renderers.items()}, args.passes, seed0=1)
        if failed:
            raise RuntimeError(f"{group}: " + "; ".join(f"{n}: {e}" for n, e in failed.items()))
        result[group] = group_rows(methods, passes, renderers)
    return result


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--variant", default="cuda_ad_rgb")
    parser.add_argument("--res", type=int, default=1280)
    parser.add_argument("--spp", type=int, default=64)
    parser.add_argument("--passes", type=int, default=8)
    parser.add_argument("--scenes", nargs="+", default=["material_studio", "interior"])
    parser.add_argument("--maps", nargs="+", default=["scene", "tests/data/envmaps/forest_slope_1k.hdr"],
                        help="map files, or 'scene' for the scene's own")
    parser.add_argument("--groups", nargs="+", default=list(GROUPS), choices=GROUPS)
    parser.add_argument("--path-depth", type=int, default=4)
    parser.add_argument("--prb-depth", type=int, default=3)
    parser.add_argument("--freeze", action="store_true", help="time recorded (dr.freeze) passes")
    parser.add_argument("--json")
    args = parser.parse_args(argv)

    import mitsuba as mi
    mi.set_variant(args.variant)
    import mitsuba_shsampling  # noqa: F401  (registers the plugins)
    from mitsuba_shsampling.scenes import builtin_scenes

    start = time.perf_counter()
    cells = []
    print(f"{'scene':<16} {'map':<22} {'method':<22} {'vs':<12} {'variance':>8} {'pass time':>9} "
          f"{'efficiency':>10} {'mean diff':>9} {'set-up s':>8}")
    for scene in args.scenes:
        for envmap in args.maps:
            rows = measure_cell(builtin_scenes()[scene], None if envmap == "scene" else envmap, args)
            name = envmap.rsplit("/", 1)[-1]
            cells.append({"scene": scene, "map": name, "groups": rows})
            for group in rows.values():
                for method, row in group.items():
                    if "against" in row:
                        print(f"{scene:<16} {name:<22} {method:<22} {row['against']:<12} {row['variance_ratio']:8.2f} "
                              f"{row['time_ratio']:9.2f} {row['efficiency_ratio']:10.2f} {row['mean_rel_diff']:+9.4f} "
                              f"{row['setup_s']:8.2f}", flush=True)
    seconds = time.perf_counter() - start
    print(f"variance, pass time, efficiency: ratios to the group's best Mitsuba method ('vs'); took {seconds:.0f} s")
    if args.json:
        with open(args.json, "w") as f:
            json.dump({"command": " ".join(["python3", "scripts/bench_device.py"] + (argv or sys.argv[1:])),
                       "variant": args.variant, "args": vars(args), "seconds": seconds, "cells": cells}, f, indent=1)
    return 0


if __name__ == "__main__":
    sys.exit(main())
