"""How far the quadrature's per-material differences are from what the pilots measure, and the
prior of ``integrators/material_pilots.py`` fitted to them.

For each cell (the realistic scenes under the five maps with ``sh_direct`` and ``sh_path``
``max_depth`` 4 at 480 x 360, the nine spheres under the five maps with ``sh_direct`` at
128 x 96, as the README's tables), the default plan is made and, for every material and product
strategy its pilots measured, the calibrated quadrature's difference (environment less the
strategy), the pilots' measured one with its standard error, and the material's environment
variance (quadrature and pilot) are kept. Then the two-part prior (``MATERIAL_PRIOR_SD``,
``MISSED_SHARE``) is fitted by maximum likelihood on a grid, beside the best single normal prior.

    python scripts/bench_material_pilots.py --json docs/bench_material_pilots.json

``--plans FILE`` also writes each cell's plan; ``--against FILE`` (another commit's ``--plans``) lists
the plans that changed, for an A/B of each (``scripts/ab_interleaved.py``).
"""

from __future__ import annotations

import argparse
import glob
import json
import os

import numpy as np

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
SPHERES = ["sphere_diffuse", "sphere_ggx005", "sphere_ggx010", "sphere_ggx020", "sphere_ggx030", "sphere_ggx050",
           "sphere_roughplastic", "sphere_principled", "sphere_conductor"]


def cells(quick: bool = False) -> list:
    maps = [None] + sorted(glob.glob(os.path.join(ROOT, "tests", "data", "envmaps", "*.hdr")))
    out = []
    for scene in ["material_studio", "interior"]:
        for envmap in maps:
            out.append((scene, envmap, 480, {"type": "sh_direct"}))
            out.append((scene, envmap, 480, {"type": "sh_path", "max_depth": 4}))
    out += [(scene, envmap, 128, {"type": "sh_direct"}) for scene in SPHERES for envmap in maps]
    return out[:2] if quick else out


def measurements(cell, plans: dict | None = None) -> list:
    """The plan of one cell and its per-material measurements, as dicts; the plan itself
    goes into ``plans`` (cell name -> :func:`plan_summary`) where given."""
    import mitsuba as mi

    from mitsuba_shsampling.scenes import builtin_scenes, load_scene

    scene_name, envmap, res, integrator = cell
    scene = load_scene(builtin_scenes()[scene_name], envmap=envmap, res=res, spp=16)
    choice = mi.load_dict(integrator).plan(scene)
    name = f"{scene_name}|{os.path.basename(envmap) if envmap else 'sunsky'}|{integrator['type']}"
    if plans is not None:
        plans[name] = plan_summary(choice.as_dict())
    if choice.pilots is None:
        return []
    factor = {s.label: f for s, f in choice.pilots.calibration.items()}
    rows = []
    for key, by_strategy in choice.pilots.by_material.items():
        for strategy, m in by_strategy.items():
            q = dict(m.quadrature)
            env = q["environment"] * factor.get("environment", 1.0)
            rows.append({"cell": name, "material": key, "strategy": strategy.label,
                         "predicted": env - q[strategy.label] * factor.get(strategy.label, 1.0),
                         "measured": m.difference, "error": m.error, "environment": env,
                         "environment_pilot": m.environment})
    return rows


def plan_summary(plan: dict) -> dict:
    """What a plan runs: each material's strategy, or "lean" for every material where the
    lean kernel runs (Mitsuba's strategies without the product's code)."""
    return {m["name"]: "lean" if plan.get("lean") else m["strategy"] for m in plan["materials"]}


def changed_plans(before: dict, after: dict) -> dict:
    """Cell -> material -> (strategy before, after), for the cells of both whose plans differ."""
    out = {}
    for cell in sorted(set(before) & set(after)):
        a, b = before[cell], after[cell]
        moved = {m: (a.get(m), b.get(m)) for m in sorted(set(a) | set(b)) if a.get(m) != b.get(m)}
        if moved:
            out[cell] = moved
    return out


def log_likelihood(rows: list, close: float, missed_share: float) -> float:
    """Of the measured differences under the two-part prior (each measurement normal with its error)."""
    predicted, measured, error, env, wide = (np.array([r[k] for r in rows]) for k in
                                             ("predicted", "measured", "error", "environment", "wide"))
    near, far = (close * env) ** 2 + error ** 2, wide ** 2 + error ** 2
    d2 = (measured - predicted) ** 2
    log_near = np.log1p(-missed_share) - 0.5 * d2 / near - 0.5 * np.log(near)
    if missed_share <= 0:
        return float(np.sum(log_near))
    log_far = np.log(missed_share) - 0.5 * d2 / far - 0.5 * np.log(far)
    return float(np.sum(np.logaddexp(log_near, log_far)))


def fit(rows: list) -> dict:
    """The two-part prior's maximum-likelihood (close, missed share) on a grid, and the best
    single normal prior (missed share 0)."""
    usable = [dict(r, wide=max(r["environment_pilot"], r["environment"])) for r in rows
              if r["environment"] > 0 and r["error"] > 0]
    grid = [(log_likelihood(usable, c, w), c, w) for c in np.linspace(0.005, 0.5, 100)
            for w in np.linspace(0.001, 0.5, 200)]
    best, close, share = max(grid)
    single = max((log_likelihood(usable, c, 0.0), c) for c in np.linspace(0.005, 1.0, 200))
    precise = [r for r in usable if r["error"] < 0.05 * r["environment"]]
    off = np.array([abs(r["measured"] - r["predicted"]) / r["environment"] for r in precise])
    return {"measurements": len(usable), "close": float(close), "missed_share": float(share),
            "log_likelihood": best, "single_normal": {"close": float(single[1]), "log_likelihood": single[0]},
            "precise": len(precise),
            "precise_off": {"median": float(np.median(off)) if len(off) else None,
                            "p90": float(np.percentile(off, 90)) if len(off) else None,
                            "max": float(off.max()) if len(off) else None}}


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--json", default=None)
    parser.add_argument("--quick", action="store_true", help="two cells only (a smoke run)")
    parser.add_argument("--plans", default=None, help="write each cell's plan (material -> strategy) to this JSON")
    parser.add_argument("--against", default=None, help="a --plans JSON of another commit: list the plans that changed")
    args = parser.parse_args(argv)
    from mitsuba_shsampling.benchmarks import set_default_variant

    set_default_variant()
    import mitsuba_shsampling  # noqa: F401  (registers the plugins)

    rows, plans = [], {}
    for cell in cells(args.quick):
        rows += measurements(cell, plans)
    if args.plans:
        with open(args.plans, "w") as f:
            json.dump(plans, f, indent=1, sort_keys=True)
    if args.against:
        with open(args.against) as f:
            changed = changed_plans(json.load(f), plans)
        print(f"plans changed against {args.against}: {len(changed)} of {len(plans)}")
        for cell, moved in changed.items():
            print(f"  {cell}: " + ", ".join(f"{m} {a} -> {b}" for m, (a, b) in moved.items()))
    result = fit(rows)
    print(f"{result['measurements']} measured differences; two-part prior: close {result['close']:.3f} of the "
          f"environment variance, missed share {result['missed_share']:.3f} (log-likelihood "
          f"{result['log_likelihood']:.1f}); best single normal: {result['single_normal']['close']:.3f} "
          f"({result['single_normal']['log_likelihood']:.1f})")
    off = result["precise_off"]
    if off["median"] is not None:
        print(f"closely measured ({result['precise']}): the quadrature off by {off['median']:.3f} of the environment "
              f"variance at the median, {off['p90']:.3f} at the 90th percentile, {off['max']:.3f} at most")
    if args.json:
        with open(args.json, "w") as f:
            json.dump({**result, "rows": rows}, f, indent=1)
        print(f"wrote {args.json}")


if __name__ == "__main__":
    main()
