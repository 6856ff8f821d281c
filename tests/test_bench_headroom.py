"""Specification: ``scripts/bench_headroom.py`` measures, per scene and map, the share of the
environment strategy's variance that the oracle at path vertex 1, 2 and 3 removes, and what
``sh_path`` removes, at equal samples."""

import json
import math
import os
import subprocess
import sys

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def test_headroom_per_vertex_and_sh_path_s_share_of_it(tmp_path):
    out = tmp_path / "headroom.json"
    env = dict(os.environ, PYTHONPATH=REPO + os.pathsep + os.environ.get("PYTHONPATH", ""))
    proc = subprocess.run([sys.executable, os.path.join(REPO, "scripts", "bench_headroom.py"), "--scenes", "sphere_ggx010",
                           "--maps", "scene", "--res", "24", "--spp", "2", "--passes", "3", "--resolution", "8",
                           "--json", str(out)], env=env, capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr
    (cell,) = json.loads(out.read_text())["cells"]
    rows = cell["rows"]
    assert set(rows) == {"baseline", "oracle at 1", "oracle at 2", "oracle at 3", "sh_path"}
    assert rows["baseline"]["saving"] == 0.0
    for name, row in rows.items():
        assert row["variance"] > 0 and math.isclose(row["saving"], 1 - row["variance"] / rows["baseline"]["variance"])
