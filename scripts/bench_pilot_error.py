"""How well do the pilots' standard errors say how far their film variances scatter?

Per cell (scene x map), ``sh_direct``'s plan is made with ``--seeds`` different pilot seeds;
each pilot's film variance and its standard error (``integrators/pilots.py``:
``film_variance_and_error``) are kept, and the standard deviation of the film variances over the
seeds is divided by the mean of their errors: about 1 where the error is right, above 1 where it
says the pilots measured more closely than they did. Prints a table and writes JSON.

    python scripts/bench_pilot_error.py [--cells material_studio:studio_small_03 interior:forest_slope]
        [--seeds 8] [--res 480] [--json OUT]

A map is a name under tests/data/envmaps (``NAME_1k.hdr``) or ``own`` (the scene's own map).
"""

from __future__ import annotations

import argparse
import json
import os

import numpy as np

os.environ.setdefault("SHSAMPLING_CACHE_DIR", "off")  # every plan made afresh

import mitsuba_shsampling  # noqa: E402
from mitsuba_shsampling.benchmarks import set_default_variant  # noqa: E402

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
CELLS = ["material_studio:studio_small_03", "interior:forest_slope", "material_preview:potsdamer_platz",
         "material_studio:immenstadter_horn", "interior:studio_small_03", "sphere_roughplastic:studio_small_03"]


def seeds_of(scene_name: str, map_name: str, seeds: int, res: int) -> dict:
    """Pilot -> (film variances, errors) over ``seeds`` pilot seeds."""
    import mitsuba as mi
    from mitsuba_shsampling.integrators import pilots
    from mitsuba_shsampling.scenes import builtin_scenes, load_scene
    envmap = None if map_name == "own" else os.path.join(REPO, "tests", "data", "envmaps", f"{map_name}_1k.hdr")
    out, first = {}, pilots.PILOT_SEED
    try:
        for k in range(seeds):
            pilots.PILOT_SEED = first + 1000 * k
            scene = load_scene(builtin_scenes()[scene_name], envmap=envmap, res=res, spp=16)
            measured = mi.load_dict({"type": "sh_direct", "plan_file": ""}).plan(scene).pilots
            for name, value in measured.image_variance.items():
                values, errors = out.setdefault(name, ([], []))
                values.append(value)
                errors.append(measured.image_variance_error[name])
    finally:
        pilots.PILOT_SEED = first
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--cells", nargs="+", default=CELLS, help="SCENE:MAP")
    parser.add_argument("--seeds", type=int, default=8)
    parser.add_argument("--res", type=int, default=480)
    parser.add_argument("--json", default=None)
    args = parser.parse_args()
    if args.seeds < 3:
        parser.error("--seeds must be >= 3 for a scatter")
    set_default_variant()
    rows = []
    print(f"{'cell':45s} {'pilot':14s} {'mean':>10s} {'scatter':>10s} {'error':>10s} {'ratio':>6s}")
    for cell in args.cells:
        scene_name, map_name = cell.split(":")
        for name, (values, errors) in seeds_of(scene_name, map_name, args.seeds, args.res).items():
            scatter, error = float(np.std(values, ddof=1)), float(np.mean(errors))
            rows.append({"cell": cell, "pilot": name, "mean": float(np.mean(values)), "scatter": scatter,
                         "error": error, "ratio": scatter / error if error > 0 else float("nan"),
                         "values": values, "errors": errors})
            r = rows[-1]
            print(f"{cell:45s} {name:14s} {r['mean']:10.4g} {scatter:10.3g} {error:10.3g} {r['ratio']:6.2f}", flush=True)
    ratios = [r["ratio"] for r in rows if np.isfinite(r["ratio"])]
    print(f"scatter / error: median {np.median(ratios):.2f}, {min(ratios):.2f}-{max(ratios):.2f} over {len(ratios)}")
    if args.json:
        with open(args.json, "w") as f:
            json.dump({"res": args.res, "seeds": args.seeds, "rows": rows}, f, indent=1)


if __name__ == "__main__":
    main()
