"""Specification: ``scripts/bench_cost_breakdown.py`` measures every stage of a product
lane and the three whole passes, and writes them as JSON (issue 21, its first deliverable)."""

import json
import os
import subprocess
import sys

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))

STAGES = ("lobe", "sh_levels", "product_levels", "proxy_levels", "pyramid_descent", "leaf_placement",
          "product_sample", "product_pdf", "bsdf_eval_pdf", "shadow_ray", "envmap_eval", "bsdf_sample",
          "bsdf_ray", "product_code_fused", "cosine_table_sample", "cosine_table_pdf", "mitsuba_envmap_sample")
PASSES = ("direct", "sh_direct_environment", "sh_direct_product")


def run_tiny(tmp_path) -> dict:
    out = tmp_path / "cost.json"
    scene = os.path.join(REPO, "mitsuba_shsampling", "scenes", "sphere_ggx010.xml")
    env = dict(os.environ, PYTHONPATH=REPO + os.pathsep + os.environ.get("PYTHONPATH", ""))
    proc = subprocess.run([sys.executable, os.path.join(REPO, "scripts", "bench_cost_breakdown.py"), scene,
                           "--res", "24", "--spp", "1", "--repeats", "1", "--json", str(out)],
                          env=env, capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr
    assert "pass: sh_direct_product" in proc.stdout
    return json.loads(out.read_text())


def test_every_stage_and_pass_is_measured_and_the_product_pass_has_the_most_operations(tmp_path):
    report = run_tiny(tmp_path)
    rows = {(row["kind"], row["key"]): row for row in report["rows"]}
    for key in STAGES:
        row = rows[("stage", key)]
        assert row["kernel_ops"] > 0, key
        assert row["kernels"] == (0 if key == "proxy_levels" else 1), key  # a difference, or one kernel
        if row["kernels"]:
            assert row["ms_per_2p20_lanes"] >= 0, key
        else:  # the difference of two timed stages: at this tiny size their noise can make it negative
            whole, part = (rows[("stage", k)] for k in row["difference_of"])
            assert row["execution_ms"] == whole["execution_ms"] - part["execution_ms"], key
    for key in PASSES:
        assert rows[("pass", key)]["lanes"] == report["camera_samples"] == 24 * 24
    for key in PASSES:  # each pass is also timed replayed from a dr.freeze recording
        assert rows[("pass", key)]["frozen"] and rows[("pass", key)]["frozen_wall_ms"] > 0, key
    ops = {key: rows[("pass", key)]["kernel_ops"] for key in PASSES}
    assert ops["sh_direct_product"] > ops["sh_direct_environment"] > 0 and ops["direct"] > 0
    # The whole walk is its levels, the descent and the placement (each kernel also loads
    # its inputs and stores its outputs, hence the slack).
    parts = sum(rows[("stage", key)]["kernel_ops"] for key in ("product_levels", "pyramid_descent", "leaf_placement"))
    assert 0.9 < parts / rows[("stage", "product_sample")]["kernel_ops"] < 1.2
