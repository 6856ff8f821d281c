"""Specification: a regular (non-editable) install is self-contained: it ships the
built-in scenes and their maps, and finds them without the source tree."""

import json
import os
import shutil
import subprocess
import sys
import sysconfig
import textwrap

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))

CHECK = textwrap.dedent("""
    import json, os, sys
    import mitsuba as mi
    mi.set_variant("llvm_ad_rgb")
    import mitsuba_shsampling
    from mitsuba_shsampling import scenes
    path = scenes.default_scene_path()
    scene = scenes.load_scene(path, res=4)
    print(json.dumps({"package": mitsuba_shsampling.__file__, "scene": path,
                      "envmaps": sorted(scenes.builtin_envmaps()),
                      "has_envmap": scenes.scene_envmap(scene) is not None}))
""")


def test_a_non_editable_install_ships_and_finds_the_builtin_scenes(tmp_path):
    venv = tmp_path / "venv"
    subprocess.run([sys.executable, "-m", "venv", "--without-pip", str(venv)], check=True)
    python = str(venv / "bin" / "python")
    # Dependencies (mitsuba, drjit, numpy, ...) come from this interpreter's site-packages,
    # added as a plain path: its .pth files (an editable install of this package) are not run.
    site = subprocess.run([python, "-c", "import sysconfig; print(sysconfig.get_paths()['purelib'])"],
                          check=True, capture_output=True, text=True).stdout.strip()
    with open(os.path.join(site, "dependencies.pth"), "w") as f:
        f.write(sysconfig.get_paths()["purelib"] + "\n")
    # Build from a copy of what a source distribution holds, so no build/ lands in the work tree.
    source = tmp_path / "source"
    shutil.copytree(os.path.join(REPO, "mitsuba_shsampling"), source / "mitsuba_shsampling",
                    ignore=shutil.ignore_patterns("__pycache__"))
    for name in ("pyproject.toml", "README.md"):
        shutil.copy(os.path.join(REPO, name), source)
    install = subprocess.run([sys.executable, "-m", "pip", "--python", python, "install", "--quiet",
                              "--no-deps", str(source)], capture_output=True, text=True, timeout=300)
    assert install.returncode == 0, install.stderr

    run = subprocess.run([python, "-c", CHECK], cwd=tmp_path, capture_output=True, text=True, timeout=300,
                         env={k: v for k, v in os.environ.items() if k != "PYTHONPATH"})
    assert run.returncode == 0, run.stderr
    found = json.loads(run.stdout.strip().splitlines()[-1])
    assert found["package"].startswith(site)
    assert found["scene"].startswith(site) and os.path.isfile(found["scene"])
    assert found["has_envmap"]
    assert found["envmaps"] == ["studio", "sunsky"]
