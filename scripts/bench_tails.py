"""Heavy-tail check: brightest pixel and per-pixel variance over many samples.

Renders one scene with several methods on a large film at low spp (many
samples in few launches), the same seeds for every method, and prints per
method: the brightest pixel (luminance), the 99.99 % quantile of the pixel
luminance, the per-pixel variance across passes (mean over pixels, i.e. the
expected squared error of one pass, tails included) and its ratio to
Mitsuba's ``direct``, and the median warm time of a pass.

    python scripts/bench_tails.py [SCENE.xml] --envmap MAP --res 1024 --spp 4 --passes 6 \
        --methods direct,direct_misc,sh_direct --set sh_direct:defensive_share=0.05 --json OUT.json

``--set METHOD:key=value`` adds an integrator parameter (repeatable); a method
name ``NAME+TAG`` runs integrator NAME under its own label (so one plugin can
run with several settings); ``--share-sweep 0.05,0.1,0.2`` adds one sh_direct
row per defensive share.
"""

from __future__ import annotations

import argparse
import json
import statistics
import time

import numpy as np

import mitsuba_shsampling  # noqa: F401  (points Dr.Jit at a usable libLLVM first)
import mitsuba as mi


def luminance(image: np.ndarray) -> np.ndarray:
    return image[..., 0] * 0.2126 + image[..., 1] * 0.7152 + image[..., 2] * 0.0722


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("scene", nargs="?", default=None)
    parser.add_argument("--envmap", default=None)
    parser.add_argument("--res", type=int, default=1024)
    parser.add_argument("--spp", type=int, default=4)
    parser.add_argument("--passes", type=int, default=6)
    parser.add_argument("--methods", default="direct,direct_misc,sh_direct")
    parser.add_argument("--share-sweep", default="", help="defensive shares for extra sh_direct rows")
    parser.add_argument("--set", action="append", default=[], help="METHOD:key=value")
    parser.add_argument("--json", default=None)
    args = parser.parse_args()

    mi.set_variant("llvm_ad_rgb")
    mitsuba_shsampling.register()
    from mitsuba_shsampling.scenes import load_scene, unit_scene_path

    path = args.scene or unit_scene_path()
    extra: dict[str, dict] = {}
    for item in args.set:
        name, assignment = item.split(":", 1)
        key, value = assignment.split("=", 1)
        extra.setdefault(name, {})[key] = json.loads(value)

    methods = []
    for name in args.methods.split(","):
        base_name = name.split("+")[0]
        kind = {"direct": ("direct", False), "direct_misc": ("direct", True),
                "env_only": ("direct", False)}.get(base_name, (base_name, False))
        methods.append((name, {"type": kind[0], **extra.get(name, {})}, kind[1]))
    for share in filter(None, args.share_sweep.split(",")):
        methods.append((f"sh_direct@{share}", {"type": "sh_direct", "defensive_share": float(share),
                                                **extra.get("sh_direct", {})}, False))

    rows = []
    for name, desc, compensated in methods:
        scene = load_scene(path, envmap=args.envmap, mis_compensation=compensated, res=args.res, spp=args.spp)
        integrator = mi.load_dict(desc)
        mi.render(scene, integrator=integrator, seed=10_000, spp=args.spp)  # compile, untimed
        passes, times = [], []
        for seed in range(args.passes):
            start = time.perf_counter()
            image = np.array(mi.render(scene, integrator=integrator, seed=seed, spp=args.spp))
            times.append(time.perf_counter() - start)
            passes.append(luminance(image))
        stack = np.stack(passes)
        variance = stack.var(axis=0, ddof=1)
        rows.append({
            "method": name, "integrator": desc,
            "max_pixel": float(stack.max()),
            "q9999": float(np.quantile(stack, 0.9999)),
            "mean": float(stack.mean()),
            "pixel_variance": float(variance.mean()),
            "time_s": statistics.median(times),
            "samples": int(args.passes * args.res * args.res * args.spp),
        })
    base = next((r for r in rows if r["method"] == "direct"), rows[0])
    print(f"{'method':22s} {'max px':>9s} {'q99.99':>8s} {'mean':>8s} {'pix var':>10s} {'var/dir':>8s}"
          f" {'time s':>7s} {'t/dir':>6s} {'eff/dir':>7s}")
    for r in rows:
        r["variance_ratio"] = r["pixel_variance"] / base["pixel_variance"]
        r["time_ratio"] = r["time_s"] / base["time_s"]
        r["efficiency_ratio"] = 1.0 / (r["variance_ratio"] * r["time_ratio"])
        print(f"{r['method']:22s} {r['max_pixel']:9.2f} {r['q9999']:8.3f} {r['mean']:8.4f} {r['pixel_variance']:10.3e}"
              f" {r['variance_ratio']:8.3f} {r['time_s']:7.3f} {r['time_ratio']:6.2f} {r['efficiency_ratio']:7.2f}")
    if args.json:
        with open(args.json, "w") as f:
            json.dump({"scene": path, "envmap": args.envmap, "res": args.res, "spp": args.spp,
                       "passes": args.passes, "rows": rows}, f, indent=1)


if __name__ == "__main__":
    main()
