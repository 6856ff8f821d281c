"""Bias check with many independent passes: one compare method against a Mitsuba `path` reference.

    python scripts/bias_check.py SCENE.xml [--method sh_direct] [--envmap MAP] [--passes 64]

The statistic is the report's (``mitsuba_shsampling.report.metrics.bias_test``):
each pass of the method and each reference pass (``path`` at the method's
family depth) gives one number, its image-mean luminance; Welch's t-test
compares their means. Flagged when p < 1e-3 (two-sided), the report's
false-alarm rate. Use it when a report flags a method: the seeds here are
independent of the report's, and more passes narrow the test.
"""

from __future__ import annotations

import argparse
import json

import mitsuba as mi
import numpy as np


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("scene")
    parser.add_argument("--method", default="sh_direct", help="a compare method name (default %(default)s)")
    parser.add_argument("--envmap")
    parser.add_argument("--passes", type=int, default=64)
    parser.add_argument("--spp", type=int, default=16)
    parser.add_argument("--ref-passes", type=int, default=16)
    parser.add_argument("--ref-spp", type=int, default=256)
    parser.add_argument("--res", type=int, default=64)
    parser.add_argument("--max-depth", type=int, default=2)
    args = parser.parse_args()

    mi.set_variant("llvm_ad_rgb")
    import mitsuba_shsampling  # noqa: F401  (registers the integrators)
    from mitsuba_shsampling.report import metrics
    from mitsuba_shsampling.report.methods import available_methods, is_multi_bounce
    from mitsuba_shsampling.report.rendering import MethodRenderer, load_for_settings, reference_integrator

    try:
        runnable, notes = available_methods([args.method], multi_bounce=is_multi_bounce(args.max_depth))
    except ValueError as err:
        parser.error(str(err))
    if not runnable:
        parser.error(notes[0])
    method = runnable[0]
    settings = {"res": args.res, "sampler": "independent", "envmap": args.envmap, "max_depth": args.max_depth}
    tested = MethodRenderer(args.scene, method, settings)
    scene, sensor = load_for_settings(args.scene, settings)
    reference = mi.load_dict(reference_integrator(method.family, args.max_depth))

    ref = metrics.image_mean_luminance(np.stack([
        np.array(mi.render(scene, sensor=sensor, integrator=reference, spp=args.ref_spp, seed=50_000 + k))
        for k in range(args.ref_passes)]))
    est = metrics.image_mean_luminance(np.stack([tested.render(args.spp, 700_000 + k)[0]
                                                 for k in range(args.passes)]))
    test = metrics.bias_test(est, ref)
    print(json.dumps({"scene": args.scene, "envmap": args.envmap, "method": method.name,
                      "passes": args.passes, "spp": args.spp, "reference_passes": args.ref_passes,
                      "reference_spp": args.ref_spp, "mean": test.mean, "reference_mean": test.reference_mean,
                      "t": test.t, "dof": test.dof, "p_value": test.p_value, "alpha": test.alpha,
                      "flagged": test.flagged}))


if __name__ == "__main__":
    main()
