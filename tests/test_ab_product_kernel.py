"""Specification: ``scripts/ab_product_kernel.py`` times the product sample and pdf walk of the
working tree against a git revision's, in one process, and writes both as JSON (issue 21:
every change to the walk states by how much it moved)."""

import json
import os
import subprocess
import sys

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
WALK_MODULES = [os.path.join("mitsuba_shsampling", *path) for path in (
    ("warp", "product.py"), ("warp", "hierarchy.py"), ("warp", "hsw.py"), ("warp", "proxy_lobe.py"),
    ("warp", "env_leaves.py"), ("envmap", "pyramid.py"))]


def walk_is_committed() -> bool:
    """The working tree's walk modules equal HEAD's (as on a clean clone)."""
    return subprocess.run(["git", "diff", "--quiet", "HEAD", "--", *WALK_MODULES], cwd=REPO).returncode == 0


def test_both_versions_are_timed_and_head_loads_as_the_same_code(tmp_path):
    out = tmp_path / "ab.json"
    scene = os.path.join(REPO, "mitsuba_shsampling", "scenes", "sphere_ggx010.xml")
    env = dict(os.environ, PYTHONPATH=REPO + os.pathsep + os.environ.get("PYTHONPATH", ""))
    proc = subprocess.run([sys.executable, os.path.join(REPO, "scripts", "ab_product_kernel.py"), scene,
                           "--base", "HEAD", "--res", "24", "--spp", "1", "--repeats", "2", "--json", str(out)],
                          cwd=REPO, env=env, capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr
    report = json.loads(out.read_text())
    assert report["lanes"] > 0 and report["repeats"] == 2
    assert [row["kernel"] for row in report["rows"]] == ["sample", "pdf"]
    for row in report["rows"]:
        assert len(row["base_samples"]) == len(row["tree_samples"]) == 2
        assert row["base_ms"] > 0 and row["tree_ms"] > 0 and row["ratio"] > 0
        assert row["base_ops"] > 0 and row["tree_ops"] > 0
        if walk_is_committed():
            # The copy loaded from git is the working tree's code: it traces the same kernel.
            assert row["base_ops"] == row["tree_ops"], row
