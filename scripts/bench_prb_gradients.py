"""Per-pass gradient variance of ``sh_prb`` against Mitsuba's ``prb`` at equal time.

On the material studio (``prb_studio.py``: float ground albedo), at the optimisation's
starting point (``bench_inverse.py``'s ``roughness_texture``: knot roughness 0.3 instead of 0.1, grey ground) with
the L2 loss against a ``path`` render of the true scene, every pass renders and
backpropagates the loss with one integrator and reads the gradients of: the knot's GGX
roughness, the plastic ball's GGX roughness, the ground's albedo texture, the envmap's
``scale`` and its texels. Passes are interleaved (pass k of every method before pass k + 1
of any, same seeds), so a slow spell of the machine falls on all alike; each method first
runs two passes untimed (compilation; Mitsuba's envmap texels get no gradient in the first
differentiable pass).

Variance of a parameter's gradient: across passes, summed over its elements for textures
(the expected squared error of one pass). ``efficiency vs prb`` = (variance x time) of
``prb`` / that of the method: how many times fewer seconds the method needs for the same
gradient error (> 1: it wins); its interval comes from resampling the passes.
``prb + mis_compensation`` is ``prb`` on the studio with the envmap's ``mis_compensation`` on.

    python scripts/bench_prb_gradients.py --res 96 --spp 4 --passes 96 --json prb_gradients.json
"""

from __future__ import annotations

import argparse
import json
import time

import drjit as dr
import mitsuba as mi
import numpy as np

import prb_studio as studio


def parameter_names(params) -> dict[str, str]:
    """Label -> scene parameter key of every gradient measured."""
    scale, data = studio.envmap_keys(params)
    return {"knot roughness (GGX)": studio.ROUGHNESS, "plastic roughness (GGX)": studio.PLASTIC_ROUGHNESS,
            "ground albedo texture": studio.TEXTURE, "envmap scale": scale, "envmap texels": data}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--res", type=int, default=96, help="image width (height at the studio's aspect)")
    parser.add_argument("--spp", type=int, default=4, help="samples per pixel of each pass")
    parser.add_argument("--passes", type=int, default=32)
    parser.add_argument("--target-spp", type=int, default=4096)
    parser.add_argument("--json", default=None)
    args = parser.parse_args()

    mi.set_variant("llvm_ad_rgb")  # registers the plugins (prb_studio imported the package)
    target = studio.render_target(args.res, args.target_spp)

    runs = {}
    for name, (plugin, mis_compensation) in studio.METHODS.items():
        scene = studio.load_studio(args.res, mis_compensation)
        params = mi.traverse(scene)
        studio.set_start(params)
        keys = parameter_names(params)
        for key in keys.values():
            dr.enable_grad(params[key])
        params.update()
        runs[name] = dict(scene=scene, params=params, keys=keys, integrator=mi.load_dict(plugin),
                          grads={label: [] for label in keys}, times=[])

    def one_pass(run, seed):
        image = mi.render(run["scene"], run["params"], integrator=run["integrator"], spp=args.spp,
                          seed=2 * seed, seed_grad=2 * seed + 1)
        dr.backward(dr.mean(dr.square(image - target), axis=None))
        grads = {label: np.ravel(dr.grad(run["params"][key]).numpy()) for label, key in run["keys"].items()}
        for key in run["keys"].values():
            dr.set_grad(run["params"][key], 0.0)
        return grads

    for run in runs.values():
        for seed in (10_000, 10_001):
            one_pass(run, seed)
    for k in range(args.passes):
        for run in runs.values():
            start = time.perf_counter()
            grads = one_pass(run, k)
            run["times"].append(time.perf_counter() - start)
            for label, g in grads.items():
                run["grads"][label].append(g)

    records = []
    base = runs["prb"]
    base_time = float(np.median(base["times"]))
    # Squared distance of each pass's gradient from the mean: the variance is their mean, and
    # resampling passes gives its interval (the tails of one pass's error are heavy).
    squared = {name: {label: np.square(np.stack(g) - np.stack(g).mean(axis=0)).sum(axis=1) * args.passes
                      / (args.passes - 1) for label, g in run["grads"].items()} for name, run in runs.items()}
    resamples = np.random.default_rng(1).integers(0, args.passes, (1000, args.passes))
    print(f"material studio {args.res} px wide, {args.spp} spp per pass, {args.passes} passes, L2 loss at the "
          "optimisation's start; [5 %, 95 %] of the efficiency over resampled passes")
    print(f"{'method':24s} {'s/pass':>7s}  {'parameter':24s} {'mean gradient':>14s} {'variance':>11s} "
          f"{'var ratio prb/x':>15s} {'efficiency vs prb':>17s} {'interval':>15s}")
    for name, run in runs.items():
        seconds = float(np.median(run["times"]))
        for label, g in run["grads"].items():
            mean = float(np.stack(g).mean(axis=0).sum())
            variance = float(squared[name][label].mean())
            ratio = float(squared["prb"][label].mean()) / variance
            efficiency = ratio * base_time / seconds
            resampled = (squared["prb"][label][resamples].mean(axis=1)
                         / squared[name][label][resamples].mean(axis=1) * base_time / seconds)
            low, high = (float(q) for q in np.quantile(resampled, [0.05, 0.95]))
            records.append({"method": name, "parameter": label, "seconds_per_pass": seconds,
                            "mean_gradient_sum": mean, "variance": variance, "variance_ratio_prb_over": ratio,
                            "efficiency_vs_prb": efficiency, "efficiency_interval_90": [low, high],
                            "res": args.res, "spp": args.spp, "passes": args.passes})
            print(f"{name:24s} {seconds:7.3f}  {label:24s} {mean:14.4g} {variance:11.4g} {ratio:15.2f} "
                  f"{efficiency:17.2f} {f'[{low:.2f}, {high:.2f}]':>15s}")
    if args.json:
        with open(args.json, "w") as f:
            json.dump(records, f, indent=1)
        print(f"wrote {args.json}")


if __name__ == "__main__":
    main()
