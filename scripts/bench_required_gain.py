"""Does the plan's bar for the product (``REQUIRED_GAIN``) sit where the product starts to pay?

Per cell (scene x map): the plan's best assignment with a product strategy and its predicted
gain over the lean kernel (``product_candidate``, in a fresh process), then that assignment
forced against every material on ``environment``, timed interleaved at equal time
(``scripts/ab_interleaved.py``, frozen passes, in another fresh process). Cells whose candidate
is predicted outside ``--near`` are listed but not rendered. Prints a table and writes JSON.

    python scripts/bench_required_gain.py [--family sh_direct] [--scenes material_studio interior]
        [--maps sunsky tests/data/envmaps/*.hdr] [--res 480] [--passes 12] [--near 0.9 1.4] [--json OUT]
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))

PLAN_CODE = """
import json, sys
import mitsuba_shsampling
from mitsuba_shsampling.benchmarks import set_default_variant
set_default_variant()
import mitsuba as mi
from mitsuba_shsampling.scenes import builtin_scenes, load_scene
scene_name, envmap, res, integrator = sys.argv[1], sys.argv[2] or None, int(sys.argv[3]), json.loads(sys.argv[4])
scene = load_scene(builtin_scenes().get(scene_name, scene_name), envmap=envmap, res=res, spp=16)
plan = mi.load_dict(integrator).plan(scene).as_dict()
print("PLAN " + json.dumps({"lean": plan["lean"], "candidate": plan["product_candidate"]}))
"""


def plan_of(scene: str, envmap: str | None, res: int, integrator: dict) -> dict:
    """The plan's lean flag and product candidate, made in a fresh process."""
    result = subprocess.run([sys.executable, "-c", PLAN_CODE, scene, envmap or "", str(res), json.dumps(integrator)],
                            capture_output=True, text=True, cwd=REPO)
    lines = [line for line in result.stdout.splitlines() if line.startswith("PLAN ")]
    if result.returncode != 0 or not lines:
        raise RuntimeError(f"planning {scene} under {envmap}: {result.stderr[-2000:]}")
    return json.loads(lines[-1][5:])


def measured_gain(scene: str, envmap: str | None, res: int, spp: int, passes: int, lean: dict,
                  forced: dict) -> dict:
    """``forced`` against ``lean`` at equal time (``scripts/ab_interleaved.py``)."""
    from mitsuba_shsampling.scenes import builtin_scenes
    with tempfile.TemporaryDirectory(prefix="required_gain_") as folder:
        out = os.path.join(folder, "ab.json")
        command = [sys.executable, os.path.join(REPO, "scripts", "ab_interleaved.py"),
                   builtin_scenes().get(scene, scene), "--res", str(res), "--spp", str(spp),
                   "--passes", str(passes), "--json", out, json.dumps(lean), json.dumps(forced)]
        if envmap:
            command += ["--envmap", envmap]
        result = subprocess.run(command, capture_output=True, text=True, cwd=REPO)
        if result.returncode != 0:
            raise RuntimeError(f"timing {scene} under {envmap}: {result.stderr[-2000:]}")
        with open(out) as f:
            row = json.load(f)["rows"][1]
    return {"measured": row["efficiency_ratio"], "variance_ratio": row["variance_ratio"],
            "time_ratio": row["time_ratio"]}


def run(family: str, scenes: list, maps: list, res: int, spp: int, passes: int, near: tuple) -> list:
    """One row per cell: the plan (lean or not), its candidate's predicted gain, and where
    that is within ``near``, the measured one."""
    print(f"{'scene':<20} {'map':<22} {'plan':<8} {'predicted':>9} {'measured':>9} {'var':>6} {'time':>6}")
    rows = []
    for scene in scenes:
        for envmap in maps:
            integrator = {"type": family, **({"max_depth": 4} if family == "sh_path" else {})}
            plan = plan_of(scene, None if envmap == "sunsky" else envmap, res, integrator)
            candidate = plan["candidate"]
            row = {"scene": scene, "map": os.path.splitext(os.path.basename(envmap))[0], "lean": plan["lean"],
                   "predicted": candidate.get("predicted_gain"), "strategies": candidate.get("strategies")}
            if candidate and near[0] <= candidate["predicted_gain"] <= near[1]:
                forced = dict(integrator, strategy=",".join(f"{k}={v}" for k, v in candidate["strategies"].items()))
                row.update(measured_gain(scene, None if envmap == "sunsky" else envmap, res, spp, passes,
                                         dict(integrator, strategy="environment"), forced))
            rows.append(row)
            number = (lambda key, digits=2: f"{row[key]:.{digits}f}" if row.get(key) is not None else "-")
            print(f"{scene:<20} {row['map']:<22} {'lean' if row['lean'] else 'product':<8} "
                  f"{number('predicted'):>9} {number('measured'):>9} {number('variance_ratio'):>6} "
                  f"{number('time_ratio'):>6}", flush=True)
    return rows


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--family", choices=["sh_direct", "sh_path"], default="sh_direct")
    parser.add_argument("--scenes", nargs="+", default=["material_studio", "interior"])
    parser.add_argument("--maps", nargs="+", default=None,
                        help="map files, or sunsky for the scene's own (default: sunsky and the test maps)")
    parser.add_argument("--res", type=int, default=480)
    parser.add_argument("--spp", type=int, default=16)
    parser.add_argument("--passes", type=int, default=12)
    parser.add_argument("--near", type=float, nargs=2, default=(0.9, 1.4),
                        help="render only candidates predicted within this range")
    parser.add_argument("--json")
    args = parser.parse_args(argv)
    maps = args.maps or ["sunsky"] + sorted(os.path.join("tests", "data", "envmaps", name)
                                            for name in os.listdir(os.path.join(REPO, "tests", "data", "envmaps"))
                                            if name.endswith(".hdr"))
    rows = run(args.family, args.scenes, maps, args.res, args.spp, args.passes, tuple(args.near))
    if args.json:
        with open(args.json, "w") as f:
            json.dump({"family": args.family, "res": args.res, "spp": args.spp, "passes": args.passes,
                       "rows": rows}, f, indent=1)
        print(f"wrote {args.json}")


if __name__ == "__main__":
    main()
