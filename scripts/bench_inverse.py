"""Three inverse problems, ``sh_prb`` against Mitsuba's ``prb`` with and without
``mis_compensation``: loss and parameter error against wall-clock seconds.

Tasks (each from a start away from the truth, Adam on the L2 image loss against a
``path`` render of the truth, one differentiable render per step):

- ``roughness_texture``: the material studio; the copper knot's GGX roughness (true 0.1,
  start 0.3) and the ground's albedo texture (16 x 16 texels, start a flat grey).
- ``envmap``: the gold GGX 0.1 sphere on its ground (``sphere_ggx010``), the camera not
  seeing the map (``hide_emitters``); the map's texels (``potsdamer_platz`` averaged to
  64 x 32; start: a flat grey of its mean).
- ``materials``: the material studio; seven parameters of five materials (the knot's, the
  gold and chrome balls', the plastic ball's and the bumped plastic's roughness, and the
  two plastics' diffuse colours), each started away from its value.

Every step is frozen (``mitsuba_shsampling.freeze``: ``dr.freeze`` of render, loss and
backward, as Mitsuba's documentation shows for optimisation loops), recorded twice before
the clock starts and replayed. ``sh_prb`` plans on the host every ``--plan-every`` steps
(``integrator.plan(scene)``, inside its clock; one ``sh_prb`` run per value given, 16 and 64
by default): it rebuilds its sampling state only where the parameters moved more than
``rebuild_tolerance``. Each method runs in a process of its own (:func:`worker`: in one
process every frozen step also reads the other methods' scenes), and the steps are
interleaved (one step of each method in turn, on the parent's command); each method's clock
counts only its own steps, until it has used ``--seconds``. At each tenth of the budget (and thrice in its first twentieth: :data:`SCORE_TIMES`),
outside the clock, the parameters are scored (in the parent):
the image loss of a ``path`` render against the same render (same seed) of the true
parameters, so that most of their noise cancels, and the task's parameter error.

    python scripts/bench_inverse.py [--tasks ...] [--seeds 3] [--seconds 20] [--res 128]
                                    [--json docs/bench_inverse.json] [--plot docs/bench_inverse.png]
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import json
import multiprocessing
import os
import statistics
import tempfile
import time
from typing import Callable

import drjit as dr
import mitsuba as mi
import numpy as np

import prb_studio as studio

HERE = os.path.dirname(os.path.abspath(__file__))
MAP = os.path.join(HERE, "..", "tests", "data", "envmaps", "potsdamer_platz_1k.hdr")
MAP_SIZE = (32, 64)
"""Rows and columns of the ``envmap`` task's unknown map."""

REFERENCES = {  # name -> (plugin, the envmap's own mis_compensation, plan every (None: no plan))
    "prb": ({"type": "prb"}, False, None),
    "prb + mis_compensation": ({"type": "prb"}, True, None),
}


def methods(plan_every: list) -> dict:
    """``sh_prb`` once per ``--plan-every`` value (its ``rebuild_interval`` the same: for the
    traced renders it is what the plan calls are for the frozen steps), then Mitsuba's two."""
    ours = {f"sh_prb (plan every {n})" if len(plan_every) > 1 else "sh_prb":
            ({"type": "sh_prb", "rebuild_interval": n}, False, n) for n in plan_every}
    return {**ours, **REFERENCES}


SCORE_TIMES = (0.0, 1 / 80, 1 / 40, 1 / 20) + tuple(k / 10 for k in range(1, 11))
"""When each method is scored, as shares of the clock budget: each tenth, and three times
in the first twentieth, where the loss falls fastest (at 20 s a budget the tenths alone
cannot tell when a method reaches a loss its rival had at 2 s)."""


@dataclasses.dataclass
class Task:
    """One inverse problem: its scene, its unknowns (parameter keys), where they start,
    their bounds and how far they are from the truth."""

    name: str
    load: Callable[[int, bool], mi.Scene]
    """(width, mis_compensation) -> the scene with its true parameters."""
    start: dict
    """Unknown (a parameter key, or ``envmap``: :func:`key_in`) -> starting value (None: the
    map's mean)."""
    bounds: dict
    """Unknown -> (low, high) after each step."""
    lr: float
    hide_emitters: bool = False
    truth: dict = dataclasses.field(default_factory=dict)
    weights: dict = dataclasses.field(default_factory=dict)
    """Unknown -> per-value weights of the parameter error (where the image depends on it)."""

    def parameter_error(self, params) -> float:
        """The unknowns' relative error, the mean over keys of |x - x*|_w / |x*|_w (weighted
        L2 over each key's values: a roughness, a colour, a texture's texels)."""
        errors = []
        for name, truth in self.truth.items():
            value, w = np.asarray(params[key_in(params, name)].numpy(), np.float64).ravel(), self.weights[name]
            errors.append(np.sqrt(np.sum(w * (value - truth) ** 2) / np.sum(w * truth ** 2)))
        return float(np.mean(errors))


def studio_task(name: str, start: dict, bounds: dict, lr: float) -> Task:
    return Task(name, lambda res, misc: studio.load_studio(res, misc), start, bounds, lr)


def envmap_scene(res: int, mis_compensation: bool) -> mi.Scene:
    from mitsuba_shsampling.scenes import builtin_scenes, load_scene

    return load_scene(builtin_scenes()["sphere_ggx010"], envmap=small_map(), res=res,
                      mis_compensation=mis_compensation)


def small_map() -> str:
    """``potsdamer_platz`` averaged to :data:`MAP_SIZE` (an EXR in the temporary folder)."""
    rows, columns = MAP_SIZE
    path = os.path.join(tempfile.gettempdir(), f"bench_inverse_potsdamer_{columns}x{rows}.exr")
    if not os.path.exists(path):
        image = np.array(mi.Bitmap(MAP), dtype=np.float32)
        image = image.reshape(rows, image.shape[0] // rows, columns, image.shape[1] // columns, 3).mean(axis=(1, 3))
        mi.Bitmap(image).write(path)
    return path


MATERIALS = {  # key -> start (true values: the studio's own)
    studio.ROUGHNESS: 0.3, "gold_ball.bsdf.alpha.value": 0.4, "chrome_ball.bsdf.alpha.value": 0.3,
    studio.PLASTIC_ROUGHNESS: 0.4, "bumped_plastic.nested_bsdf.alpha": 0.5,
    "plastic_ball.bsdf.diffuse_reflectance.value": 0.5, "bumped_plastic.nested_bsdf.diffuse_reflectance.value": 0.5,
}


def tasks() -> dict:
    colour = (0.0, 1.0)
    return {
        "roughness_texture": studio_task("roughness_texture", {studio.ROUGHNESS: 0.3, studio.TEXTURE: 0.35},
                                         {studio.ROUGHNESS: (0.01, 1.0), studio.TEXTURE: colour}, 0.02),
        "envmap": Task("envmap", envmap_scene, {"envmap": None}, {"envmap": (0.0, 1e4)}, 0.05, hide_emitters=True),
        "materials": studio_task("materials", dict(MATERIALS),
                                 {k: (0.01, 1.0) if "alpha" in k else colour for k in MATERIALS}, 0.02),
    }


def key_in(params, name: str) -> str:
    """The parameter key of an unknown: ``envmap`` names the (unnamed) map's texels, whose
    key holds an address that differs per scene."""
    if name != "envmap":
        return name
    return next(k for k in params.keys() if k.endswith(".data")
                and params.properties[k][2].class_name() == "EnvironmentMapEmitter")


def starting_values(task: Task, params) -> dict:
    """Unknown -> starting value; the map's: a flat grey of its mean."""
    return {name: float(np.mean(params[key_in(params, name)].numpy())) if value is None else value
            for name, value in task.start.items()}


def set_start(params, start: dict) -> None:
    for name, value in start.items():
        key = key_in(params, name)
        current = params[key]
        if dr.is_tensor_v(current):
            params[key] = type(current)(np.full(dr.shape(current), value, np.float32))
        else:  # opaque, as an optimiser's values are: a literal would be recorded apart
            params[key] = dr.opaque(type(current), value)
    params.update()


def sensitivity(scene, names, spp) -> dict:
    """Unknown -> |d mean(image) / d value| per value, by ``prb`` at many samples per pixel."""
    params = mi.traverse(scene)
    values = {}
    for name in names:
        key = key_in(params, name)
        values[name] = type(params[key])(params[key])
        dr.enable_grad(values[name])
        params[key] = values[name]
    params.update()
    image = mi.render(scene, params, integrator=mi.load_dict({"type": "prb"}), spp=64 * spp, seed=1, seed_grad=2)
    dr.backward(dr.mean(image, axis=None))
    weights = {}
    for name, value in values.items():
        grad = np.abs(np.asarray(dr.grad(value).numpy(), np.float64)).ravel()
        # Scalars and colours weigh their values alike; textures and maps by where the image sees them.
        weights[name] = grad if grad.size > 3 else np.ones_like(grad)
        params[key_in(params, name)] = dr.detach(value)
    params.update()
    return weights


def frozen_step(spp: int):
    import mitsuba_shsampling

    def render_loss_backward(scene, params, integrator, seed, target):
        image = mi.render(scene, params, integrator=integrator, spp=spp, seed=seed)
        loss = dr.mean(dr.square(image - target), axis=None)
        dr.backward(loss)
        return loss

    return mitsuba_shsampling.freeze(render_loss_backward)


def integrator_for(plugin: dict, task: Task) -> mi.Integrator:
    return mi.load_dict({**plugin, **({"hide_emitters": True} if task.hide_emitters else {})})


def step(run: dict, task: Task, target, args, seed: int) -> None:
    """One Adam step: the optimiser's values into the scene, for ``sh_prb`` a plan every
    ``--plan-every`` steps, then the frozen render + loss + backward, the update and the bounds."""
    params, opt, integrator = run["params"], run["opt"], run["integrator"]
    params.update(opt)
    if run["plan_every"] is not None and run["step"] % run["plan_every"] == 0:
        integrator.plan(run["scene"])
    run["frozen"](run["scene"], params, integrator, dr.opaque(mi.UInt32, seed), target)
    opt.step()
    for key, (low, high) in run["bounds"].items():
        opt[key] = dr.clip(opt[key], low, high)
    dr.eval(*(opt[key] for key in run["bounds"]))
    run["step"] += 1


def state_of(run):
    scenes = getattr(run["integrator"], "scenes", None)
    return scenes.get(run["scene"], stale_ok=True) if scenes is not None else None


def new_run(task: Task, plugin: dict, misc: bool, plan_every: int | None, target, args) -> dict:
    scene = task.load(args.res, misc)
    params = mi.traverse(scene)
    start = starting_values(task, params)
    bounds = {key_in(params, name): task.bounds[name] for name in start}
    run = dict(scene=scene, params=params, integrator=integrator_for(plugin, task), frozen=frozen_step(args.spp),
               start=start, bounds=bounds, step=0, plan_every=plan_every, target=target)

    def reset():
        set_start(params, start)
        run["opt"] = mi.ad.Adam(lr=task.lr, params={key: params[key] for key in bounds})

    # Two steps outside the clock: the first records, the second records again (Dr.Jit makes the
    # literals that changed opaque); then back to the start.
    reset()
    for k in range(2):
        step(run, task, target, args, seed=1_000_000 + k)
    reset()
    run.update(step=0, clock=0.0, step_times=[], history=[], builds=0, state=state_of(run))
    return run


def worker(conn, task_name: str, method: tuple, target: np.ndarray, seed: int, args) -> None:
    """One method's optimisation in a process of its own, stepping on the parent's command.

    Why a process each: a frozen function reads every registered Mitsuba object as an input,
    so in one process each method's parameter updates (and the scorer's) made the others'
    steps record again (6-13 recordings a run with three methods, 20-34 with four; alone, `prb`
    records twice), a cost no user with one optimisation pays. Commands: ``step`` (reply: its seconds, and whether the
    sampling state was rebuilt), ``params`` (reply: name -> values), ``done`` (reply: the
    frozen function's recordings)."""
    mi.set_variant("llvm_ad_rgb")
    import mitsuba_shsampling  # noqa: F401  (registers sh_prb in this process)

    task = tasks()[task_name]
    plugin, misc, every = method
    run = new_run(task, plugin, misc, every, mi.TensorXf(target), args)
    conn.send("ready")
    step_index = 0
    while True:
        command = conn.recv()
        if command == "step":
            start = time.perf_counter()
            step(run, task, run["target"], args, seed=2 * (seed * 100_000 + step_index))
            seconds = time.perf_counter() - start
            step_index += 1
            state = state_of(run)
            rebuilt, run["state"] = state is not run["state"], state
            conn.send((seconds, rebuilt))
        elif command == "params":
            conn.send({name: np.array(run["params"][key_in(run["params"], name)].numpy()) for name in task.start})
        else:
            conn.send(run["frozen"].n_recordings)
            return


@contextlib.contextmanager
def worker_processes(target, arguments: dict, runs: dict):
    """One spawned process per method running ``target(conn, *arguments[name])``, its end of
    the pipe as ``runs[name]["conn"]``; the block starts once each has said ``ready``, and
    every process is joined (killed after a minute) when it ends."""
    context = multiprocessing.get_context("spawn")
    for name, args in arguments.items():
        here, there = context.Pipe()
        process = context.Process(target=target, args=(there, *args))
        process.start()
        runs[name].update(conn=here, process=process)
    try:
        for run in runs.values():
            if run["conn"].recv() != "ready":
                raise RuntimeError("a worker failed to start")
        yield runs
    finally:
        for run in runs.values():
            run["process"].join(timeout=60)
            if run["process"].is_alive():
                run["process"].kill()


def run_task(task: Task, seed: int, args) -> dict:
    """One seed of one task: every method's history (each method in a process of its own,
    :func:`worker`; the scoring here)."""
    truth_scene = task.load(args.res, False)
    truth_params = mi.traverse(truth_scene)
    names = list(task.start)
    task.truth = {name: np.asarray(truth_params[key_in(truth_params, name)].numpy(), np.float64).ravel()
                  for name in names}
    task.weights = sensitivity(truth_scene, names, args.spp)
    path = mi.load_dict({"type": "path", "max_depth": 6, "hide_emitters": task.hide_emitters})
    target = np.mean([np.array(mi.render(truth_scene, integrator=path, spp=1024, seed=k))
                      for k in range(args.target_spp // 1024)], axis=0)
    scorer = task.load(args.res, False)
    scorer_params = mi.traverse(scorer)

    def scoring_render():
        return np.array(mi.render(scorer, integrator=path, spp=args.eval_spp, seed=123))

    reference = scoring_render()
    runs = {name: dict(step=0, clock=0.0, step_times=[], history=[], builds=0) for name in methods(args.plan_every)}
    workers = {name: (task.name, method, target, seed, args) for name, method in methods(args.plan_every).items()}

    def score(run):
        run["conn"].send("params")
        values = run["conn"].recv()
        for name in names:
            key = key_in(scorer_params, name)
            scorer_params[key] = type(scorer_params[key])(values[name])
        scorer_params.update()
        run["history"].append({"step": run["step"], "seconds": run["clock"],
                               "loss": float(np.mean(np.square(scoring_render() - reference))),
                               "parameter_error": task.parameter_error(scorer_params)})

    with worker_processes(worker, workers, runs):
        for run in runs.values():
            score(run)
        while any(run["clock"] < args.seconds for run in runs.values()):
            for run in runs.values():
                if run["clock"] >= args.seconds:
                    continue
                run["conn"].send("step")
                seconds, rebuilt = run["conn"].recv()
                run["step"] += 1
                run["step_times"].append(seconds)
                run["clock"] += seconds
                run["builds"] += rebuilt
                if len(run["history"]) < len(SCORE_TIMES) and run["clock"] >= SCORE_TIMES[len(run["history"])] * args.seconds:
                    score(run)
        for run in runs.values():
            run["conn"].send("done")
            run["recordings"] = run["conn"].recv()
    return {name: {"steps": run["step"], "seconds": run["clock"], "state_builds": run["builds"],
                   "recordings": run["recordings"],
                   "median_step_s": float(np.median(run["step_times"])),
                   "mean_step_s": run["clock"] / run["step"], "history": run["history"]}
            for name, run in runs.items()}


def time_to_reach(history: list, loss: float) -> float | None:
    """The first scored clock time at which the loss is <= ``loss`` (None: never)."""
    return next((h["seconds"] for h in history if h["loss"] <= loss), None)


def late_mean(history: list, key: str, seconds: float) -> float:
    """The mean of ``key`` over the scores of the budget's second half: where the loss has
    settled to the noise of the method's gradients, one score is one draw of that noise."""
    return float(np.mean([h[key] for h in history if h["seconds"] >= seconds / 2] or [history[-1][key]]))


def summarise(results: dict, seconds: float) -> dict:
    """Per task and method: medians over the seeds of the step time (and its ratio to
    ``prb``'s), the final loss and parameter error, their means over the second half
    (:func:`late_mean`), and, per seed, the time to reach each reference's second-half
    mean loss as a share of the budget (inf: never)."""
    summary = {}
    for task, seeds in results.items():
        summary[task] = {}
        for method in next(iter(seeds.values())):
            runs = [seeds[s][method] for s in seeds]
            row = {"median_step_s": statistics.median(r["median_step_s"] for r in runs),
                   "step_ratio_to_prb": statistics.median(r["median_step_s"] / seeds[s]["prb"]["median_step_s"]
                                                          for s, r in zip(seeds, runs)),
                   "mean_step_s": statistics.median(r["mean_step_s"] for r in runs),
                   "state_builds": statistics.median(r["state_builds"] for r in runs),
                   "recordings": statistics.median(r.get("recordings", 0) for r in runs),
                   "final_loss": statistics.median(r["history"][-1]["loss"] for r in runs),
                   "final_parameter_error": statistics.median(r["history"][-1]["parameter_error"] for r in runs),
                   "late_loss": statistics.median(late_mean(r["history"], "loss", seconds) for r in runs),
                   "late_parameter_error": statistics.median(late_mean(r["history"], "parameter_error", seconds)
                                                             for r in runs)}
            for reference in ("prb", "prb + mis_compensation"):
                shares, ratios = [], []
                for s, r in zip(seeds, runs):
                    level = late_mean(seeds[s][reference]["history"], "loss", seconds)
                    reached = time_to_reach(r["history"], level)
                    own = time_to_reach(seeds[s][reference]["history"], level)
                    shares.append(reached / seconds if reached is not None else float("inf"))
                    ratios.append(reached / own if reached is not None and own else float("inf"))
                row[f"time_to_{reference}_late_loss"] = shares
                # The measure: the time to the reference's loss over the reference's own time to it.
                row[f"time_ratio_to_{reference}"] = statistics.median(ratios)
            summary[task][method] = row
    return summary


def print_summary(summary: dict) -> None:
    print("medians over the seeds; 'late': the mean over the budget's second half; time to reach: the "
          "share of the budget at which a seed's loss first reaches the reference's late loss")
    print(f"{'task':18s} {'method':24s} {'step s':>7s} {'x prb':>6s} {'mean s':>7s} {'builds':>6s} {'records':>7s} "
          f"{'late loss':>10s} {'late error':>10s} {'final error':>11s}  time to prb's / prb+misc's late loss "
          "(per seed; median over its own time)")
    for task, rows in summary.items():
        for method, row in rows.items():
            shares = lambda key: " ".join("never" if not np.isfinite(x) else f"{x:.2f}" for x in row[key])  # noqa: E731
            print(f"{task:18s} {method:24s} {row['median_step_s']:7.3f} {row['step_ratio_to_prb']:6.2f} "
                  f"{row['mean_step_s']:7.3f} {row['state_builds']:6.0f} {row['recordings']:7.0f} "
                  f"{row['late_loss']:10.3g} {row['late_parameter_error']:10.3f} {row['final_parameter_error']:11.3f}  "
                  f"{shares('time_to_prb_late_loss')} ({row['time_ratio_to_prb']:.2f}) / "
                  f"{shares('time_to_prb + mis_compensation_late_loss')} "
                  f"({row['time_ratio_to_prb + mis_compensation']:.2f})")


def plot(results: dict, path: str, args) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    ours = iter(("tab:red", "tab:orange", "tab:purple", "tab:brown"))
    colours = {name: {"prb": "tab:blue", "prb + mis_compensation": "tab:green"}.get(name) or next(ours)
               for name in next(iter(next(iter(results.values())).values()))}
    fig, axes = plt.subplots(len(results), 2, figsize=(11, 3.2 * len(results)), squeeze=False)
    for row, (task, seeds) in zip(axes, results.items()):
        for ax, key, title in zip(row, ("loss", "parameter_error"), ("image loss", "parameter error (relative)")):
            for seed, runs in seeds.items():
                for method, run in runs.items():
                    ax.plot([h["seconds"] for h in run["history"]], [h[key] for h in run["history"]],
                            color=colours[method], alpha=0.8, lw=1.2, label=method if seed == next(iter(seeds)) else None)
            ax.set_yscale("log")
            ax.set_title(f"{task}: {title}", fontsize=10)
            ax.set_xlabel("wall-clock seconds (own steps, re-plans included)")
            ax.grid(True, which="both", alpha=0.3)
        row[0].legend(fontsize=8)
    fig.suptitle(f"sh_prb against prb: three inverse problems, {len(next(iter(results.values())))} seeds each, "
                 f"{args.res} px, {args.spp} spp a step, {args.seconds:.0f} s a method", fontsize=11)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    print(f"wrote {path}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--tasks", nargs="*", default=None, help="of: roughness_texture envmap materials (all)")
    parser.add_argument("--seeds", type=int, default=3)
    parser.add_argument("--seconds", type=float, default=20.0, help="clock budget of each method and seed")
    parser.add_argument("--res", type=int, default=128)
    parser.add_argument("--spp", type=int, default=4, help="samples per pixel of a step")
    parser.add_argument("--plan-every", type=int, nargs="+", default=[16, 64],
                        help="sh_prb: steps between plan(scene) calls (one sh_prb run per value)")
    parser.add_argument("--eval-spp", type=int, default=64)
    parser.add_argument("--target-spp", type=int, default=4096)
    parser.add_argument("--json", default=None)
    parser.add_argument("--plot", default=None)
    parser.add_argument("--from-json", default=None, help="summarise (and plot) a run's JSON again, run nothing")
    args = parser.parse_args()
    if args.from_json:
        with open(args.from_json) as f:
            written = json.load(f)
        args.__dict__.update({k: v for k, v in written["settings"].items() if k not in ("json", "plot", "from_json")})
        written["summary"] = summarise(written["runs"], args.seconds)
        print_summary(written["summary"])
        if args.json:
            with open(args.json, "w") as f:
                json.dump(written, f, indent=1)
        if args.plot:
            plot(written["runs"], args.plot, args)
        return

    mi.set_variant("llvm_ad_rgb")
    chosen = tasks()
    names = args.tasks or list(chosen)
    results = {name: {} for name in names}
    for name in names:
        for seed in range(args.seeds):
            results[name][seed] = run_task(chosen[name], seed, args)
            print(f"{name} seed {seed}: " + ", ".join(
                f"{m} {r['steps']} steps ({r['state_builds']} builds, {r['recordings']} recordings), "
                f"loss {r['history'][-1]['loss']:.3g}" for m, r in results[name][seed].items()),
                flush=True)
    summary = summarise(results, args.seconds)
    print_summary(summary)
    if args.json:
        with open(args.json, "w") as f:
            json.dump({"settings": vars(args), "summary": summary, "runs": results}, f, indent=1)
        print(f"wrote {args.json}")
    if args.plot:
        plot(results, args.plot, args)


if __name__ == "__main__":
    main()
