"""Specification: ``scripts/bench_gradient_plans.py`` takes gradients of an inverse problem's
loss with ``sh_prb``'s two plans, its forced strategies and Mitsuba's ``prb`` (with and without
``mis_compensation``), and gives each method's gradient variance, step time and efficiency over
the image plan's."""

import json
import math
import os
import subprocess
import sys

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
SCRIPTS = os.path.join(REPO, "scripts")


def test_the_envmap_task_at_its_truth_gives_every_methods_gradient_variance_and_efficiency(tmp_path):
    out = tmp_path / "gradients.json"
    env = dict(os.environ, PYTHONPATH=REPO + os.pathsep + os.environ.get("PYTHONPATH", ""))
    proc = subprocess.run([sys.executable, os.path.join(SCRIPTS, "bench_gradient_plans.py"), "--tasks", "envmap",
                           "--points", "truth", "--samples", "3", "--res", "16", "--spp", "2", "--target-spp", "1024",
                           "--json", str(out)], env=env, capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr[-3000:]
    rows = json.loads(out.read_text())["results"]["envmap"]["truth"]
    assert set(rows) == {"sh_prb (gradient plan)", "sh_prb (image plan)", "sh_prb environment", "sh_prb product",
                         "prb", "prb + mis_compensation"}
    assert rows["sh_prb (image plan)"]["variance_over_plan"] == 1.0
    assert rows["sh_prb (image plan)"]["efficiency_over_plan"] == 1.0
    for row in rows.values():
        assert math.isfinite(row["variance_over_plan"]) and row["variance_over_plan"] > 0
        assert row["median_step_s"] > 0
    assert "image plan" in proc.stdout and "efficiency / plan" in proc.stdout
