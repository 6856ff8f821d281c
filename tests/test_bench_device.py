"""Specification: ``scripts/bench_device.py`` (the GPU benchmark) renders each group of
methods interleaved and reports this package's methods against the group's best Mitsuba
method; run here on ``llvm_ad_rgb`` at a few pixels. ``scripts/trim_wheel.py`` keeps a
wheel's RECORD true to what it keeps."""

import base64
import hashlib
import importlib.util
import json
import math
import os
import subprocess
import sys
import zipfile

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def load_script(name):
    spec = importlib.util.spec_from_file_location(name, os.path.join(REPO, "scripts", f"{name}.py"))
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_each_of_the_package_s_methods_is_set_against_the_best_mitsuba_method_of_its_group(tmp_path):
    out = tmp_path / "device.json"
    env = dict(os.environ, PYTHONPATH=REPO + os.pathsep + os.environ.get("PYTHONPATH", ""))
    proc = subprocess.run([sys.executable, os.path.join(REPO, "scripts", "bench_device.py"), "--variant", "llvm_ad_rgb",
                           "--res", "24", "--spp", "2", "--passes", "3", "--scenes", "sphere_ggx010", "--maps", "scene",
                           "--groups", "direct", "path", "--json", str(out)],
                          env=env, capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr
    (cell,) = json.loads(out.read_text())["cells"]
    groups = cell["groups"]
    assert set(groups) == {"direct", "path"}
    assert {m for m, r in groups["direct"].items() if "against" in r} == {"sh_direct", "sh_direct:environment"}
    assert {m for m, r in groups["path"].items() if "against" in r} == {"sh_path", "sh_path:environment"}
    for group in groups.values():
        for row in group.values():
            if "against" in row:
                assert row["against"] in group and "against" not in group[row["against"]]
                assert all(math.isfinite(row[k]) and row[k] > 0 for k in ("variance_ratio", "time_ratio"))
                assert math.isclose(row["efficiency_ratio"], 1.0 / (row["variance_ratio"] * row["time_ratio"]))


def test_a_trimmed_wheel_keeps_the_variant_asked_for_and_a_record_of_exactly_what_it_holds(tmp_path):
    trim_wheel = load_script("trim_wheel")
    wheel = tmp_path / "in" / "mitsuba-0-cp312-cp312-any.whl"
    wheel.parent.mkdir()
    members = {"mitsuba/__init__.py": b"x", "mitsuba/cuda_ad_rgb.cpython-312-x86_64-linux-gnu.so": b"a",
               "mitsuba/llvm_ad_rgb.cpython-312-x86_64-linux-gnu.so": b"b", "mitsuba/include/x.h": b"c",
               "mitsuba/plugins/volpath.so": b"d", "mitsuba/plugins/envmap.so": b"e",
               "mitsuba-0.dist-info/RECORD": b"stale"}
    with zipfile.ZipFile(wheel, "w") as z:
        for name, data in members.items():
            z.writestr(name, data)
    out = trim_wheel.trim(str(wheel), {"cuda_ad_rgb"}, str(tmp_path / "out"))
    with zipfile.ZipFile(out) as z:
        names = set(z.namelist())
        record = z.read("mitsuba-0.dist-info/RECORD").decode().split()
    assert names == {"mitsuba/__init__.py", "mitsuba/cuda_ad_rgb.cpython-312-x86_64-linux-gnu.so",
                     "mitsuba/plugins/envmap.so", "mitsuba-0.dist-info/RECORD"}
    digest = base64.urlsafe_b64encode(hashlib.sha256(b"e").digest()).rstrip(b"=").decode()
    assert f"mitsuba/plugins/envmap.so,sha256={digest},1" in record
    assert "mitsuba-0.dist-info/RECORD,," in record and len(record) == 4
