"""The bias test on real renders: Mitsuba's unbiased `direct` against independent `path` references."""

import numpy as np
from scipy import stats

import mitsuba_shsampling  # noqa: F401  (LLVM backend check)
import mitsuba as mi

mi.set_variant("llvm_ad_rgb")

from mitsuba_shsampling import scenes  # noqa: E402
from mitsuba_shsampling.report import metrics  # noqa: E402
from mitsuba_shsampling.report.rendering import load_for_settings  # noqa: E402


def test_repeated_bias_tests_of_an_unbiased_renderer_fail_at_their_stated_rate():
    # 64 independent checks, as compare runs them: 12 passes of direct (2 spp) against a
    # reference of 6 chunks of path max_depth 2 (the same estimator as direct 1+1, 8 spp).
    # Under no bias the p-values are uniform: the rate of p < alpha is alpha for every alpha.
    scene, sensor = load_for_settings(scenes.builtin_scenes()["sphere_ggx010"],
                                      {"res": 16, "sampler": "independent"})
    direct = mi.load_dict({"type": "direct"})
    path = mi.load_dict({"type": "path", "max_depth": 2})

    def pass_means(integrator, spp, seeds):
        return metrics.image_mean_luminance(np.stack([
            np.array(mi.render(scene, sensor=sensor, integrator=integrator, spp=spp, seed=s)) for s in seeds]))

    checks = 64
    p_values = np.array([
        metrics.bias_test(pass_means(direct, 2, range(1_000 + 12 * c, 1_000 + 12 * (c + 1))),
                          pass_means(path, 8, range(900_000 + 6 * c, 900_000 + 6 * (c + 1)))).p_value
        for c in range(checks)])
    assert stats.kstest(p_values, "uniform").pvalue > 1e-3
    flagged_at_10_percent = np.count_nonzero(p_values < 0.1)
    assert flagged_at_10_percent <= 0.1 * checks + 4 * np.sqrt(checks * 0.1 * 0.9)
    assert np.count_nonzero(p_values < metrics.BIAS_ALPHA) <= 1


def test_bias_check_script_reports_the_same_statistic_for_a_compare_method():
    import json
    import os
    import subprocess
    import sys

    repo = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    proc = subprocess.run([sys.executable, os.path.join(repo, "scripts", "bias_check.py"),
                           scenes.builtin_scenes()["sphere_ggx010"], "--method", "direct_misc", "--res", "8",
                           "--passes", "8", "--spp", "2", "--ref-passes", "4", "--ref-spp", "8"],
                          cwd=repo, capture_output=True, text=True, timeout=300,
                          env=dict(os.environ, PYTHONPATH=repo))
    assert proc.returncode == 0, proc.stderr
    result = json.loads(proc.stdout.strip().splitlines()[-1])
    assert result["method"] == "direct_misc" and result["alpha"] == metrics.BIAS_ALPHA
    assert result["flagged"] == (result["p_value"] < metrics.BIAS_ALPHA)
    assert abs(result["t"]) < 10 and result["dof"] > 1
