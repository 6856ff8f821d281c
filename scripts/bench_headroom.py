"""Headroom at depth (issue 46): how much variance an ideal product sampler could still save at
path vertex k = 1, 2, 3, and how much of the first vertex's ``sh_path`` reaches.

Per scene and map, at ``--max-depth`` (default 4), equal samples: ``--passes`` renders of
``--spp`` samples per pixel of
- ``oracle_path`` with ``oracle_vertex`` 0 (the environment strategy at every vertex:
  Mitsuba's compensated envmap sampling, the baseline), and with the oracle at vertex 1, 2, 3
  (the exact tabulated product at that vertex only, ``--resolution`` cells a side);
- ``sh_path`` (its plan; the product at the first hits).
The variance is the per-pixel variance of the passes' luminance averaged over the film. The
headroom at vertex k is 1 - variance(oracle at k) / variance(baseline); ``sh_path``'s saving
is 1 - variance(sh_path) / variance(baseline), and its share of vertex 1's headroom their
ratio. Equal samples, not equal time: the oracle costs thousands of BSDF evaluations a sample
and is only a bound on what a sampler could save.

    python3 scripts/bench_headroom.py [--scenes material_studio interior sphere_ggx010 ...]
        [--maps scene FILE ...] [--res 160] [--spp 4] [--passes 8] [--resolution 16] [--json OUT.json]
"""

from __future__ import annotations

import argparse
import json
import sys
import time

import numpy as np

LUMINANCE = np.array([0.212671, 0.715160, 0.072169])


def film_variance(scene, integrator, spp: int, passes: int) -> tuple[float, float, float]:
    """(mean per-pixel variance, brightest pixel's variance, seconds a pass) of ``passes`` renders."""
    import mitsuba as mi
    images, start = [], time.perf_counter()
    for k in range(passes):
        images.append(np.array(mi.render(scene, integrator=integrator, spp=spp, seed=1 + k))[..., :3] @ LUMINANCE)
    variance = np.array(images).var(axis=0, ddof=1)
    return float(variance.mean()), float(variance.max()), (time.perf_counter() - start) / passes


def measure(scene, args) -> dict:
    import mitsuba as mi
    rows = {}
    for vertex in range(0, min(3, args.max_depth - 1) + 1):
        integrator = mi.load_dict({"type": "oracle_path", "max_depth": args.max_depth, "oracle_vertex": vertex,
                                   "resolution": args.resolution})
        mi.render(scene, integrator=integrator, spp=1, seed=0)  # compile
        rows[f"oracle at {vertex}" if vertex else "baseline"] = film_variance(scene, integrator, args.spp, args.passes)
    sh_path = mi.load_dict({"type": "sh_path", "max_depth": args.max_depth})
    mi.render(scene, integrator=sh_path, spp=1, seed=0)
    rows["sh_path"] = film_variance(scene, sh_path, args.spp, args.passes)
    base = rows["baseline"][0]
    out = {name: {"variance": v, "brightest_pixel_variance": m, "pass_s": t, "saving": 1.0 - v / base}
           for name, (v, m, t) in rows.items()}
    first = out.get("oracle at 1", {}).get("saving", 0.0)
    out["sh_path"]["share_of_vertex_1"] = out["sh_path"]["saving"] / first if first > 0 else None
    return out


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--scenes", nargs="+", default=["material_studio", "interior", "sphere_ggx010",
                                                         "sphere_roughplastic", "sphere_diffuse"])
    parser.add_argument("--maps", nargs="+", default=["scene", "tests/data/envmaps/forest_slope_1k.hdr"])
    parser.add_argument("--res", type=int, default=160)
    parser.add_argument("--spp", type=int, default=4)
    parser.add_argument("--passes", type=int, default=8)
    parser.add_argument("--max-depth", type=int, default=4)
    parser.add_argument("--resolution", type=int, default=16)
    parser.add_argument("--json")
    args = parser.parse_args(argv)

    from mitsuba_shsampling.benchmarks import set_default_variant
    set_default_variant()
    import mitsuba as mi

    import mitsuba_shsampling  # noqa: F401  (registers the plugins)
    from mitsuba_shsampling.scenes import builtin_scenes, load_scene

    cells = []
    print(f"{'scene':<20} {'map':<22} {'vertex 1':>8} {'vertex 2':>8} {'vertex 3':>8} {'sh_path':>8} {'share':>6}")
    for name in args.scenes:
        for envmap in args.maps:
            scene = load_scene(builtin_scenes()[name], envmap=None if envmap == "scene" else envmap,
                               res=args.res, spp=args.spp)
            rows = measure(scene, args)
            label = envmap.rsplit("/", 1)[-1]
            cells.append({"scene": name, "map": label, "rows": rows})
            saving = [rows.get(f"oracle at {k}", {}).get("saving", float("nan")) for k in (1, 2, 3)]
            share = rows["sh_path"]["share_of_vertex_1"]
            print(f"{name:<20} {label:<22} " + " ".join(f"{100 * s:7.1f}%" for s in saving)
                  + f" {100 * rows['sh_path']['saving']:7.1f}% " + (f"{share:6.2f}" if share is not None else "   n/a"),
                  flush=True)
    print("each column: the share of the baseline's variance (the environment strategy at every vertex) "
          "that the oracle at that vertex, or sh_path, removes")
    if args.json:
        with open(args.json, "w") as f:
            json.dump({"command": " ".join(["python3", "scripts/bench_headroom.py"] + (argv or sys.argv[1:])),
                       "variant": mi.variant(), "args": vars(args), "cells": cells}, f, indent=1)
    return 0


if __name__ == "__main__":
    sys.exit(main())
