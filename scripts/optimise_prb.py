"""Recover a roughness and an albedo texture from a target render: loss against wall-clock
seconds, ``sh_prb`` against Mitsuba's ``prb``.

The material studio (``prb_studio.py``) is rendered by ``path`` with its own parameters (the
target). Each method then starts from the copper knot's GGX roughness at 0.3 (true 0.1) and
a flat grey ground albedo texture (16 x 16 texels, true: the tiles averaged to 16 x 16) and runs Adam on the L2
image loss, one differentiable render per step. Steps are interleaved (one step of each
method in turn) and each method's clock counts only its own steps, builds of its sampling
state included, until it has used ``--seconds``. Every ``--eval-every`` steps, outside the
clock, the current parameters are scored: the image L2 loss of a ``path`` render against the
same render (same seed) of the true parameters, so that most of the noise cancels; the
roughness error; the RMSE of the texture, each texel weighted by how much the image depends
on it (most of the ground is seen far away, where its texels barely matter).

    python scripts/optimise_prb.py --seconds 40 --rebuild-intervals 16 --json optimise_prb.json --plot optimise_prb.png

With ``--freeze`` every method's step (render, loss, backward) is a frozen function
(``mitsuba_shsampling.freeze``: ``dr.freeze`` with the cycle collector paused), recorded
once and replayed; ``sh_prb`` then refreshes its sampling state outside it, with
``integrator.plan(scene)`` every ``rebuild_interval`` steps (timed with the step).
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
    parser.add_argument("--eval-spp", type=int, default=128)
    parser.add_argument("--target-spp", type=int, default=4096)
    parser.add_argument("--seed", type=int, default=0, help="offset of the steps' seeds")
    parser.add_argument("--rebuild-intervals", type=int, nargs="*", default=[],
                        help="further sh_prb runs with these rebuild_interval values")
    parser.add_argument("--json", default=None)
    parser.add_argument("--plot", default=None, help="PNG of the loss and the errors against seconds")
    parser.add_argument("--freeze", action="store_true", help="freeze each method's step (see above)")
    args = parser.parse_args()

    mi.set_variant("llvm_ad_rgb")  # registers the plugins (prb_studio imported the package)
    target = studio.render_target(args.res, args.target_spp)
    scorer = studio.load_studio(args.res)
    scorer_params = mi.traverse(scorer)
    # Copies: .numpy() can alias the texture's memory, which later updates overwrite.
    true_texture = np.array(scorer_params[studio.TEXTURE].numpy())
    sensitivity = texel_sensitivity(scorer, args.spp)
    path = mi.load_dict({"type": "path", "max_depth": 6})

    def scoring_render():
        return np.array(mi.render(scorer, integrator=path, spp=args.eval_spp, seed=123))

    # The true parameters' scoring render: every score uses its samples, so that the
    # noise of the two renders largely cancels in their difference.
    reference = scoring_render()

    methods = dict(studio.METHODS)
    for interval in args.rebuild_intervals:
        methods[f"sh_prb rebuild_interval={interval}"] = ({"type": "sh_prb", "rebuild_interval": interval}, False)

    runs = {}
    for name, (plugin, mis_compensation) in methods.items():
        scene = studio.load_studio(args.res, mis_compensation)
        params = mi.traverse(scene)
        studio.set_start(params)
        run = dict(scene=scene, params=params, integrator=mi.load_dict(plugin), step=0,
                   frozen=frozen_step(args.spp) if args.freeze else None)
        # One step outside the clock compiles the method's kernels; then back to the start.
        run["opt"] = optimiser(params, args.lr)
        step(run, target, args.spp, seed=10_000)
        studio.set_start(params)
        run.update(opt=optimiser(params, args.lr), step=0, clock=0.0, builds=0, history=[], step_times=[],
                   state=sampling_state(run))
        runs[name] = run

    def score(run):
        for key in (studio.ROUGHNESS, studio.TEXTURE):
            scorer_params[key] = dr.detach(run["params"][key])
        scorer_params.update()
        error = np.square(run["params"][studio.TEXTURE].numpy() - true_texture).sum(axis=-1)
        run["history"].append({
            "step": run["step"], "seconds": run["clock"],
            "loss": float(np.mean(np.square(scoring_render() - reference))),
            "roughness": float(run["params"][studio.ROUGHNESS][0]),
            "roughness_error": abs(float(run["params"][studio.ROUGHNESS][0]) - TRUE_ROUGHNESS),
            "texture_rmse": float(np.sqrt(np.sum(sensitivity * error) / np.sum(sensitivity) / 3))})

    for run in runs.values():
        score(run)
    while any(run["clock"] < args.seconds for run in runs.values()):
        for run in runs.values():
            if run["clock"] >= args.seconds:
                continue
            start = time.perf_counter()
            step(run, target, args.spp, seed=args.seed + run["step"])
            run["step_times"].append(time.perf_counter() - start)
            run["clock"] += run["step_times"][-1]
            state = sampling_state(run)
            run["builds"] += state is not run["state"]
            run["state"] = state
            if run["step"] % args.eval_every == 0:
                score(run)

    print(f"material studio {args.res} px wide, {args.spp} spp per step, Adam lr {args.lr}, "
          f"{args.seconds:.0f} s per method; scores: path {args.eval_spp} spp against the same render of the true "
          "parameters")
    print(f"{'method':34s} {'steps':>6s} {'s/step':>7s} {'median':>7s} {'builds':>6s} {'loss start':>11s} {'end':>10s} "
          f"{'mean over last half':>19s} {'roughness':>10s} {'texture RMSE':>12s}")
    records = {}
    for name, run in runs.items():
        first, last = run["history"][0], run["history"][-1]
        late = [h["loss"] for h in run["history"] if h["seconds"] >= args.seconds / 2]
        print(f"{name:34s} {run['step']:6d} {run['clock'] / run['step']:7.3f} {np.median(run['step_times']):7.3f} "
              f"{run['builds']:6d} "
              f"{first['loss']:11.4g} {last['loss']:10.4g} {np.mean(late):19.4g} "
              f"{last['roughness']:10.4f} {last['texture_rmse']:12.4f}")
        records[name] = {"steps": run["step"], "seconds": run["clock"], "state_builds": run["builds"],
                         "median_step_s": float(np.median(run["step_times"])),
                         "history": run["history"]}
    records["settings"] = vars(args)
    if args.json:
        with open(args.json, "w") as f:
            json.dump(records, f, indent=1)
        print(f"wrote {args.json}")
    if args.plot:
        plot(runs, args.plot, args)


def step(run, target, spp, seed):
    """One Adam step on the L2 loss of one differentiable render."""
    params, opt, integrator = run["params"], run["opt"], run["integrator"]
    params.update(opt)
    if run["frozen"] is not None:
        # The sampling state is refreshed on the host, outside the recording (a replay runs no Python).
        interval = getattr(getattr(integrator, "options", None), "rebuild_interval", None)
        if interval is not None and run["step"] % interval == 0:
            integrator.plan(run["scene"])
        run["frozen"](run["scene"], params, integrator, dr.opaque(mi.UInt32, 2 * seed), target)
    else:
        image = mi.render(run["scene"], params, integrator=integrator, spp=spp,
                          seed=2 * seed, seed_grad=2 * seed + 1)
        dr.backward(dr.mean(dr.square(image - target), axis=None))
    opt.step()
    opt[studio.ROUGHNESS] = dr.clip(opt[studio.ROUGHNESS], 0.01, 1.0)
    opt[studio.TEXTURE] = dr.clip(opt[studio.TEXTURE], 0.0, 1.0)
    dr.eval(opt[studio.ROUGHNESS], opt[studio.TEXTURE])
    run["step"] += 1


def texel_sensitivity(scene, spp):
    """(TEXTURE_RES, TEXTURE_RES) weights: the derivative of the image mean with respect to each
    albedo texel (summed over channels), by ``prb`` at many samples per pixel."""
    params = mi.traverse(scene)
    dr.enable_grad(params[studio.TEXTURE])
    params.update()
    for seed in range(2):  # the first pass only warms up
        image = mi.render(scene, params, integrator=mi.load_dict({"type": "prb"}), spp=32 * spp,
                          seed=2 * seed, seed_grad=2 * seed + 1)
        dr.set_grad(params[studio.TEXTURE], 0.0)
        dr.backward(dr.mean(image, axis=None))
    weight = np.abs(np.array(dr.grad(params[studio.TEXTURE]).numpy())).sum(axis=-1)
    dr.disable_grad(params[studio.TEXTURE])
    params.update()
    return weight


def frozen_step(spp):
    """The render, loss and backward pass of :func:`step` as one frozen function."""
    import mitsuba_shsampling

    def render_loss_backward(scene, params, integrator, seed, target):
        image = mi.render(scene, params, integrator=integrator, spp=spp, seed=seed)
        loss = dr.mean(dr.square(image - target), axis=None)
        dr.backward(loss)
        return loss

    return mitsuba_shsampling.freeze(render_loss_backward)


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
    panels = (("loss", "image L2 loss (against the true parameters)"), ("roughness_error", "|roughness - 0.1|"),
              ("texture_rmse", "albedo texture RMSE (sensitivity-weighted)"))
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
