"""The ``bench`` command: run the ``scripts/bench_*.py`` benchmarks and an error-versus-time sweep.

Contract with the benchmark scripts: each runs as
``python3 scripts/bench_<name>.py [--quick] [--json <out>/bench_<name>/bench_<name>.json]``
(each option only if the script's ``--help`` lists it) with its working
directory set to ``<out>/bench_<name>/`` (so default relative output paths
land there) and the environment variable ``SHSAMPLING_BENCH_OUT`` naming that
folder. JSON files it writes there, or new/updated ``*.json`` in the
repository's root, ``scripts/`` or ``bench/`` folders during its run, are
collected into that folder; stdout/stderr are saved as
``stdout.txt``/``stderr.txt``.
"""

from __future__ import annotations

import glob
import json
import os
import shutil
import subprocess
import sys
import time

import numpy as np
from tqdm import tqdm

from .. import scenes as builtin
from . import metrics
from .methods import available_methods
from .plots import convergence_figure
from .rendering import MethodRenderer, admissible_spp, render_reference

REPO_ROOT = os.path.normpath(os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", ".."))
SCRIPTS_DIR = os.path.join(REPO_ROOT, "scripts")


def bench_scripts() -> list[str]:
    """The ``scripts/bench_*.py`` files that exist, sorted."""
    return sorted(glob.glob(os.path.join(SCRIPTS_DIR, "bench_*.py")))


def _json_snapshot() -> dict[str, float]:
    found = {}
    for folder in (REPO_ROOT, SCRIPTS_DIR, os.path.join(REPO_ROOT, "bench")):
        for path in glob.glob(os.path.join(folder, "*.json")):
            found[path] = os.path.getmtime(path)
    return found


def _script_options(script: str, env: dict) -> str:
    """The ``--help`` text of a script (empty if it has none)."""
    try:
        proc = subprocess.run([sys.executable, script, "--help"], env=env, capture_output=True,
                              text=True, timeout=120)
    except subprocess.TimeoutExpired:
        return ""
    return proc.stdout if proc.returncode == 0 else ""


def run_script(script: str, out: str, quick: bool, timeout_s: float = 3600) -> dict:
    """Run one benchmark script; returns its status and the JSON files collected."""
    name = os.path.splitext(os.path.basename(script))[0]
    folder = os.path.abspath(os.path.join(out, name))
    os.makedirs(folder, exist_ok=True)
    before = _json_snapshot()
    env = dict(os.environ, SHSAMPLING_BENCH_OUT=folder)
    env["PYTHONPATH"] = REPO_ROOT + os.pathsep + env.get("PYTHONPATH", "")
    options = _script_options(script, env)
    argv = [sys.executable, script]
    if quick and "--quick" in options:
        argv.append("--quick")
    if "--json" in options:
        argv += ["--json", os.path.join(folder, name + ".json")]
    start = time.perf_counter()
    try:
        proc = subprocess.run(argv, cwd=folder, env=env, capture_output=True, text=True,
                              timeout=timeout_s)
        returncode, stdout, stderr = proc.returncode, proc.stdout, proc.stderr
    except subprocess.TimeoutExpired as err:
        returncode, stdout, stderr = None, err.stdout or "", f"timed out after {timeout_s} s"
    elapsed = time.perf_counter() - start
    with open(os.path.join(folder, "stdout.txt"), "w") as f:
        f.write(stdout if isinstance(stdout, str) else stdout.decode(errors="replace"))
    with open(os.path.join(folder, "stderr.txt"), "w") as f:
        f.write(stderr if isinstance(stderr, str) else stderr.decode(errors="replace"))
    for path, mtime in _json_snapshot().items():
        if before.get(path) != mtime:
            shutil.copy(path, folder)
    collected = {}
    for path in sorted(glob.glob(os.path.join(folder, "*.json"))):
        try:
            with open(path) as f:
                collected[os.path.basename(path)] = json.load(f)
        except (OSError, json.JSONDecodeError) as err:
            collected[os.path.basename(path)] = {"error": f"unreadable JSON: {err}"}
    return {"script": os.path.relpath(script, REPO_ROOT), "argv": argv[1:], "returncode": returncode,
            "time_s": elapsed, "results": collected}


def error_time_sweep(out: str, scene_path: str, settings: dict, max_spp: int, ref_spp: int,
                     cache_dir: str, progress: bool = True) -> dict:
    """MSE and warm wall time of each method at doubling spp on one scene.

    :param settings: ``res``, ``sampler``, ``envmap``, ``max_depth`` as for ``compare``.
    :returns: method name -> list of {spp, time_s, mse, rel_mse}; also writes
        ``sweep.json`` and ``sweep.png`` to ``out``.
    """
    methods, notes = available_methods(None, multi_bounce=settings["max_depth"] > 2)
    spps = sorted({admissible_spp(settings["sampler"], 2 ** i)
                   for i in range(int(np.log2(max(1, max_spp))) + 1)})
    curves: dict[str, list[dict]] = {}
    with tqdm(total=len(methods) * (len(spps) + 1), desc="error vs time", disable=not progress,
              file=sys.stderr) as bar:
        refs = {}
        for method in methods:
            if method.family not in refs:
                refs[method.family] = render_reference(scene_path, dict(settings, sampler="independent"),
                                                       method.family, ref_spp, cache_dir)
            renderer = MethodRenderer(scene_path, method, settings)
            renderer.warm_up(spps[0])
            bar.update(1)
            curves[method.name] = []
            for i, spp in enumerate(spps):
                image, elapsed = renderer.render(spp, 3_000 + i)
                ref = refs[method.family].image
                curves[method.name].append({"spp": renderer.actual_spp(), "time_s": elapsed,
                                            "mse": metrics.mse(image, ref),
                                            "rel_mse": metrics.rel_mse(image, ref)})
                bar.update(1)
    result = {"scene": scene_path, "settings": settings, "notes": notes, "curves": curves}
    with open(os.path.join(out, "sweep.json"), "w") as f:
        json.dump(result, f, indent=2)
    with open(os.path.join(out, "sweep.png"), "wb") as f:
        f.write(convergence_figure(curves, f"{os.path.basename(scene_path)}: error vs spp and time"))
    return result


def run_bench(out: str, quick: bool, res: int, sampler: str, max_spp: int, ref_spp: int,
              cache_dir: str, progress: bool = True) -> dict:
    """Run every benchmark script, then the sweep on the default scene; writes ``bench.json``."""
    os.makedirs(out, exist_ok=True)
    scripts = [run_script(s, out, quick) for s in tqdm(bench_scripts(), desc="bench scripts",
                                                       disable=not progress, file=sys.stderr)]
    settings = {"res": res, "sampler": sampler, "envmap": None, "max_depth": 2}
    sweep = error_time_sweep(out, builtin.default_scene_path(), settings, max_spp, ref_spp,
                             cache_dir, progress)
    summary = {"scripts": scripts, "sweep": sweep}
    with open(os.path.join(out, "bench.json"), "w") as f:
        json.dump(summary, f, indent=2)
    return summary
