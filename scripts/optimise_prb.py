"""Recover a roughness and an albedo texture from a target render: loss against wall-clock
seconds, ``sh_prb`` against Mitsuba's ``prb``.

The material studio (``prb_studio.py``) is rendered by ``path`` with its own parameters (the
target). Each method then starts from the copper knot's GGX roughness at 0.3 (true 0.1) and
a flat grey ground albedo texture (64 x 64 texels, true: the tiles) and runs Adam on the L2
image loss, one differentiable render per step. Steps are interleaved (one step of each
method in turn) and each method's clock counts only its own steps, builds of its sampling
state included, until it has used ``--seconds``. Every ``--eval-every`` steps, outside the
clock, the current parameters are scored: the image loss of a ``path`` render (fixed seed,
shared by all methods, so their scores share its noise) against the target, the roughness
error and the texture's RMSE against the true texture.

    python scripts/optimise_prb.py --seconds 45 --json optimise_prb.json --plot optimise_prb.png
"""

from __future__ import annotations

import argparse
import json
import time

import drjit as dr
import mitsuba as mi
import numpy as np

import prb_studio as studio

TRUE_ROUGHNESS = 0.1


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--res", type=int, default=96, help="image width (height at the studio's aspect)")
    parser.add_argument("--spp", type=int, default=4, help="samples per pixel of each step")
    parser.add_argument("--seconds", type=float, default=45.0, help="clock budget of each method")
    parser.add_argument("--lr", type=float, default=0.02, help="Adam learning rate")
    parser.add_argument("--eval-every", type=int, default=5)
    parser.add_argument("--eval-spp", type=int, default=64)
    parser.add_argument("--target-spp", type=int, default=512)
    parser.add_argument("--rebuild-intervals", type=int, nargs="*", default=[],
                        help="further sh_prb runs with these rebuild_interval values")
    parser.add_argument("--json", default=None)
    parser.add_argument("--plot", default=None, help="PNG of the loss and the errors against seconds")
    args = parser.parse_args()

    mi.set_variant("llvm_ad_rgb")  # registers the plugins (prb_studio imported the package)
    target = studio.render_target(args.res, args.target_spp)
    true_texture = mi.traverse(studio.load_studio(args.res))[studio.TEXTURE].numpy()
    scorer = studio.load_studio(args.res)
    scorer_params = mi.traverse(scorer)
    path = mi.load_dict({"type": "path", "max_depth": 6})

    methods = dict(studio.METHODS)
    for interval in args.rebuild_intervals:
        methods[f"sh_prb rebuild_interval={interval}"] = ({"type": "sh_prb", "rebuild_interval": interval}, False)

    runs = {}
    for name, (plugin, mis_compensation) in methods.items():
        scene = studio.load_studio(args.res, mis_compensation)
        params = mi.traverse(scene)
        studio.set_start(params)
        run = dict(scene=scene, params=params, integrator=mi.load_dict(plugin), step=0)
        # One step outside the clock compiles the method's kernels; then back to the start.
        run["opt"] = optimiser(params, args.lr)
        step(run, target, args.spp)
        studio.set_start(params)
        run.update(opt=optimiser(params, args.lr), step=0, clock=0.0, builds=0, history=[],
                   state=sampling_state(run))
        runs[name] = run

    def score(run):
        for key in (studio.ROUGHNESS, studio.TEXTURE):
            scorer_params[key] = dr.detach(run["params"][key])
        scorer_params.update()
        image = mi.render(scorer, integrator=path, spp=args.eval_spp, seed=123)
        texture = run["params"][studio.TEXTURE].numpy()
        run["history"].append({
            "step": run["step"], "seconds": run["clock"],
            "loss": float(np.mean(np.square(np.array(image) - np.array(target)))),
            "roughness": float(run["params"][studio.ROUGHNESS][0]),
            "roughness_error": abs(float(run["params"][studio.ROUGHNESS][0]) - TRUE_ROUGHNESS),
            "texture_rmse": float(np.sqrt(np.mean(np.square(texture - true_texture))))})

    for run in runs.values():
        score(run)
    while any(run["clock"] < args.seconds for run in runs.values()):
        for run in runs.values():
            if run["clock"] >= args.seconds:
                continue
            start = time.perf_counter()
            step(run, target, args.spp)
            run["clock"] += time.perf_counter() - start
            state = sampling_state(run)
            run["builds"] += state is not run["state"]
            run["state"] = state
            if run["step"] % args.eval_every == 0:
                score(run)

    print(f"material studio {args.res} px wide, {args.spp} spp per step, Adam lr {args.lr}, "
          f"{args.seconds:.0f} s per method; scores: path {args.eval_spp} spp against the target")
    print(f"{'method':34s} {'steps':>6s} {'s/step':>7s} {'builds':>6s} {'loss start':>11s} {'loss end':>10s} "
          f"{'roughness':>10s} {'texture RMSE':>13s}")
    records = {}
    for name, run in runs.items():
        first, last = run["history"][0], run["history"][-1]
        print(f"{name:34s} {run['step']:6d} {run['clock'] / run['step']:7.3f} {run['builds']:6d} "
              f"{first['loss']:11.4g} {last['loss']:10.4g} {last['roughness']:10.4f} {last['texture_rmse']:13.4f}")
        records[name] = {"steps": run["step"], "seconds": run["clock"], "state_builds": run["builds"],
                         "history": run["history"]}
    records["settings"] = vars(args)
    if args.json:
        with open(args.json, "w") as f:
            json.dump(records, f, indent=1)
        print(f"wrote {args.json}")
    if args.plot:
        plot(runs, args.plot, args)


def step(run, target, spp):
    """One Adam step on the L2 loss of one differentiable render."""
    params, opt = run["params"], run["opt"]
    params.update(opt)
    image = mi.render(run["scene"], params, integrator=run["integrator"], spp=spp,
                      seed=2 * run["step"], seed_grad=2 * run["step"] + 1)
    dr.backward(dr.mean(dr.square(image - target), axis=None))
    opt.step()
    opt[studio.ROUGHNESS] = dr.clip(opt[studio.ROUGHNESS], 0.01, 1.0)
    opt[studio.TEXTURE] = dr.clip(opt[studio.TEXTURE], 0.0, 1.0)
    dr.eval(opt[studio.ROUGHNESS], opt[studio.TEXTURE])
    run["step"] += 1


def optimiser(params, lr):
    return mi.ad.Adam(lr=lr, params={k: params[k] for k in (studio.ROUGHNESS, studio.TEXTURE)})


def sampling_state(run):
    """The integrator's current per-scene sampling state (None for Mitsuba's own)."""
    scenes = getattr(run["integrator"], "scenes", None)
    return scenes.get(run["scene"], stale_ok=True) if scenes is not None else None


def plot(runs, path, args):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 3, figsize=(13, 3.8))
    panels = (("loss", "image L2 loss (path render vs target)"), ("roughness_error", "|roughness - 0.1|"),
              ("texture_rmse", "albedo texture RMSE"))
    for ax, (key, title) in zip(axes, panels):
        for name, run in runs.items():
            seconds = [h["seconds"] for h in run["history"]]
            ax.plot(seconds, [h[key] for h in run["history"]], label=name)
        ax.set_yscale("log")
        ax.set_xlabel("wall-clock seconds (own steps only)")
        ax.set_title(title)
        ax.grid(True, which="both", alpha=0.3)
    axes[0].legend(fontsize=8)
    fig.suptitle(f"Material studio {args.res} px wide, {args.spp} spp per step: "
                 "recovering the knot's roughness and the ground's albedo texture")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    print(f"wrote {path}")


if __name__ == "__main__":
    main()
