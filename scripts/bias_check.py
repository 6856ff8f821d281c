"""Bias check with many independent passes: SH integrator vs a Mitsuba `path` reference.

    python scripts/bias_check.py scenes/sphere_ggx030.xml [--envmap MAP] [--passes 16]

The image mean of K passes of ``sh_direct`` (or ``--integrator``) is compared
with the mean of K independent ``path`` (max_depth 2) passes; z is the
difference over its standard error estimated from both sets. |z| < 4 means no
detectable bias. Use it when a 4-pass report flags a method: with 4 passes
the standard error has 3 degrees of freedom and |t| > 4 happens 2.8 % of the time.
"""

from __future__ import annotations

import argparse
import json

import mitsuba as mi
import numpy as np


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("scene")
    parser.add_argument("--envmap")
    parser.add_argument("--integrator", default="sh_direct")
    parser.add_argument("--passes", type=int, default=16)
    parser.add_argument("--spp", type=int, default=64)
    parser.add_argument("--ref-spp", type=int, default=512)
    parser.add_argument("--res", type=int, default=64)
    args = parser.parse_args()

    mi.set_variant("llvm_ad_rgb")
    import mitsuba_shsampling  # noqa: F401  (registers the integrators)
    from mitsuba_shsampling.scenes import load_scene

    scene = load_scene(args.scene, res=args.res, **({"envmap": args.envmap} if args.envmap else {}))
    reference = mi.load_dict({"type": "path", "max_depth": 2})
    tested = mi.load_dict({"type": args.integrator})
    ref = np.array([np.mean(mi.render(scene, integrator=reference, spp=args.ref_spp, seed=50_000 + k))
                    for k in range(args.passes)])
    est = np.array([np.mean(mi.render(scene, integrator=tested, spp=args.spp, seed=100 + k))
                    for k in range(args.passes)])
    se = np.sqrt(est.var(ddof=1) / len(est) + ref.var(ddof=1) / len(ref))
    z = float((est.mean() - ref.mean()) / se)
    print(json.dumps({"scene": args.scene, "envmap": args.envmap, "integrator": args.integrator,
                      "passes": args.passes, "mean": float(est.mean()), "reference_mean": float(ref.mean()),
                      "z": z, "unbiased_within_4_se": abs(z) < 4}))


if __name__ == "__main__":
    main()
