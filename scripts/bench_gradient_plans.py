"""Does the plan made for the image also minimise the gradients' noise? ``sh_prb``'s plan
(``strategy`` ``auto``: each material's strategy chosen for the primal image's variance at
equal time) against its plan for the gradients (``plan_for`` ``gradients``), the same
integrator with every material forced to ``environment`` or to ``product``, and Mitsuba's
``prb`` with and without ``mis_compensation``, on the three inverse problems of
``scripts/bench_inverse.py``.

For each task, at two points of an optimisation (its start, where the gradients are large,
and its truth, where only their noise is left: the noise floor the late loss sits on), each
method takes ``--samples`` gradients of the L2 image loss against the task's target (the same
frozen render + loss + backward step as ``bench_inverse.py``, ``--spp`` samples per pixel,
every sample its own seed). Per unknown (a roughness, a colour, a texture's or the map's
texels) the gradient's weighted variance ``sum_i w_i Var(g_i)``, ``w`` the sensitivity weights
of ``bench_inverse.py`` (where the image sees each texel), over its mean over the methods; a
method's variance is the mean of that over the unknowns, given over the plan's, and its
efficiency 1 / (variance x the step's median seconds), over the plan's. (Also given: the first
measure, ``sum_i w_i Var(g_i) / sum_i w_i m_i^2`` with ``m`` the mean gradient pooled over the
methods, averaged over the unknowns: at the truth, where some unknown's mean is near 0, that
unknown alone decides it.)
Each method runs in a process of its own and the steps are interleaved (one of each method in
turn), as in ``bench_inverse.py``.

    python scripts/bench_gradient_plans.py [--tasks ...] [--samples 32] [--res 128] [--spp 4]
                                           [--json docs/bench_gradient_plans.json]
"""

from __future__ import annotations

import argparse
import json
import os
import sys

import drjit as dr
import mitsuba as mi
import numpy as np

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))

import bench_inverse as inverse  # noqa: E402

METHODS = {  # name -> (plugin, the envmap's own mis_compensation)
    "sh_prb (gradient plan)": ({"type": "sh_prb", "plan_for": "gradients"}, False),
    "sh_prb (image plan)": ({"type": "sh_prb"}, False),
    "sh_prb environment": ({"type": "sh_prb", "strategy": "environment"}, False),
    "sh_prb product": ({"type": "sh_prb", "strategy": "product"}, False),
    "prb": ({"type": "prb"}, False),
    "prb + mis_compensation": ({"type": "prb"}, True),
}
PLAN = "sh_prb (image plan)"
POINTS = ("start", "truth")


def worker(conn, task_name: str, method: tuple, point: str, target: np.ndarray, args) -> None:
    """One method's gradients at one point, in a process of its own. Commands: ``grad``
    (reply: the step's seconds and unknown -> gradient values), ``done`` (reply: the plan's
    summary, or None)."""
    mi.set_variant("llvm_ad_rgb")
    import mitsuba_shsampling  # noqa: F401  (registers the plugins)

    task = inverse.tasks()[task_name]
    plugin, misc = method
    scene = task.load(args.res, misc)
    params = mi.traverse(scene)
    if point == "start":
        inverse.set_start(params, inverse.starting_values(task, params))
    keys = {name: inverse.key_in(params, name) for name in task.start}
    # Adam holds the unknowns with gradients enabled, as in an optimisation (it never steps).
    opt = mi.ad.Adam(lr=0.0, params={key: params[key] for key in keys.values()})
    params.update(opt)
    integrator = inverse.integrator_for(plugin, task)
    frozen = inverse.frozen_step(args.spp)
    target = mi.TensorXf(target)

    def gradients(seed: int):
        import time

        start = time.perf_counter()
        frozen(scene, params, integrator, dr.opaque(mi.UInt32, seed), target)
        grads = {name: dr.grad(opt[key]) for name, key in keys.items()}
        dr.eval(grads)
        dr.sync_thread()
        seconds = time.perf_counter() - start
        values = {name: np.asarray(g.numpy(), np.float64).ravel() for name, g in grads.items()}
        for key in keys.values():
            dr.clear_grad(opt[key])
        return seconds, values

    if hasattr(integrator, "plan"):
        integrator.plan(scene)
    for k in range(2):  # recorded twice before the clock, as in bench_inverse.py
        gradients(1_000_000 + k)
    conn.send("ready")
    while True:
        command = conn.recv()
        if command == "done":
            choice = integrator.choice(scene) if hasattr(integrator, "choice") else None
            conn.send(choice.summary() if choice is not None else None)
            return
        conn.send(gradients(command))


def measure(task_name: str, point: str, args) -> dict:
    """Every method's gradients at one point of one task: their relative variance, median
    step seconds and efficiency over the plan's."""
    task = inverse.tasks()[task_name]
    truth_scene = task.load(args.res, False)
    names = list(task.start)
    weights = inverse.sensitivity(truth_scene, names, args.spp)
    path = mi.load_dict({"type": "path", "max_depth": 6, "hide_emitters": task.hide_emitters})
    target = np.mean([np.array(mi.render(truth_scene, integrator=path, spp=1024, seed=k))
                      for k in range(args.target_spp // 1024)], axis=0)
    runs = {name: dict(seconds=[], grads={n: [] for n in names}) for name in METHODS}
    workers = {name: (task_name, method, point, target, args) for name, method in METHODS.items()}
    with inverse.worker_processes(worker, workers, runs):
        for k in range(args.samples):
            for run in runs.values():  # interleaved: one step of each method in turn
                run["conn"].send(k)
                seconds, values = run["conn"].recv()
                run["seconds"].append(seconds)
                for n in names:
                    run["grads"][n].append(values[n])
        for run in runs.values():
            run["conn"].send("done")
            run["plan"] = run["conn"].recv()
    pooled = {n: np.mean([np.mean(run["grads"][n], axis=0) for run in runs.values()], axis=0) for n in names}
    # Per unknown, the weighted variance over every method's mean (each unknown counts alike
    # whatever its scale: at the truth an unknown's mean gradient is near 0, and its variance
    # over its squared mean, the first measure, is dominated by it alone).
    weighted = {name: {n: float(np.sum(weights[n] * np.array(run["grads"][n]).var(axis=0, ddof=1))) for n in names}
                for name, run in runs.items()}
    mean_weighted = {n: np.mean([weighted[name][n] for name in runs]) for n in names}
    out = {}
    for name, run in runs.items():
        per_unknown = {n: weighted[name][n] / float(np.sum(weights[n] * pooled[n] ** 2)) for n in names}
        out[name] = {"relative_variance": float(np.mean(list(per_unknown.values()))), "per_unknown": per_unknown,
                     "variance_share": float(np.mean([weighted[name][n] / mean_weighted[n] for n in names])),
                     "median_step_s": float(np.median(run["seconds"])), "plan": run["plan"]}
    reference = out[PLAN]
    for row in out.values():
        row["variance_over_plan"] = row["variance_share"] / reference["variance_share"]
        row["relative_variance_over_plan"] = row["relative_variance"] / reference["relative_variance"]
        row["efficiency_over_plan"] = (reference["variance_share"] * reference["median_step_s"]
                                       / (row["variance_share"] * row["median_step_s"]))
    return out


def print_table(results: dict) -> None:
    print(f"{'task':<20}{'point':<7}{'method':<26}{'variance / plan':>16}{'step s':>9}{'efficiency / plan':>19}"
          f"{'var/mean^2':>12}{'/ plan':>8}")
    for task, points in results.items():
        for point, rows in points.items():
            for name, row in rows.items():
                print(f"{task:<20}{point:<7}{name:<26}{row['variance_over_plan']:>16.2f}{row['median_step_s']:>9.3f}"
                      f"{row['efficiency_over_plan']:>19.2f}{row['relative_variance']:>12.3g}"
                      f"{row['relative_variance_over_plan']:>8.2f}")
            print(f"{'':<27}plan: {rows[PLAN]['plan']}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--tasks", nargs="*", default=None, help="of: roughness_texture envmap materials (all)")
    parser.add_argument("--points", nargs="*", default=list(POINTS), choices=POINTS)
    parser.add_argument("--samples", type=int, default=32, help="gradients per method and point")
    parser.add_argument("--res", type=int, default=128)
    parser.add_argument("--spp", type=int, default=4)
    parser.add_argument("--target-spp", type=int, default=4096)
    parser.add_argument("--json", default=None)
    args = parser.parse_args()
    mi.set_variant("llvm_ad_rgb")
    import mitsuba_shsampling  # noqa: F401

    names = args.tasks or list(inverse.tasks())
    results = {name: {point: measure(name, point, args) for point in args.points} for name in names}
    print_table(results)
    if args.json:
        with open(args.json, "w") as f:
            json.dump({"settings": vars(args), "results": results}, f, indent=1)
        print(f"wrote {args.json}")


if __name__ == "__main__":
    main()
