"""The ``bench`` command: every benchmark of :mod:`mitsuba_shsampling.benchmarks`, then an
error-versus-time sweep.

Each benchmark's ``run(quick)`` is called in this process, in the order of
:data:`~mitsuba_shsampling.benchmarks.NAMES`; what it prints goes to
``<out>/bench_<name>/stdout.txt``, its records to ``<out>/bench_<name>/bench_<name>.json``,
and an exception to ``error.txt`` there (the remaining benchmarks still run).
"""

from __future__ import annotations

import contextlib
import json
import os
import sys
import time
import traceback

import numpy as np
from tqdm import tqdm

from .. import benchmarks
from .. import scenes as builtin
from . import metrics
from .methods import available_methods
from .plots import convergence_figure
from .rendering import MethodRenderer, admissible_spp, render_reference


def run_benchmark(name: str, out: str, quick: bool) -> dict:
    """Run one benchmark; returns its name, status, time and records."""
    folder = os.path.abspath(os.path.join(out, f"bench_{name}"))
    os.makedirs(folder, exist_ok=True)
    records, error = None, None
    start = time.perf_counter()
    with open(os.path.join(folder, "stdout.txt"), "w") as log, contextlib.redirect_stdout(log):
        try:
            records = benchmarks.benchmark(name).run(quick=quick)
        except Exception:  # one failing benchmark must not stop the others
            error = traceback.format_exc()
    elapsed = time.perf_counter() - start
    json_path = os.path.join(folder, f"bench_{name}.json")
    if error is None:
        with open(json_path, "w") as f:
            json.dump(records, f, indent=1)
    else:
        with open(os.path.join(folder, "error.txt"), "w") as f:
            f.write(error)
    return {"benchmark": name, "error": None if error is None else error.strip().splitlines()[-1],
            "time_s": elapsed, "json": json_path if error is None else None, "results": records}


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
                image, elapsed = renderer.timed_render(spp, 3_000 + i)  # each spp warmed and recorded
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
    """Run every benchmark, then the sweep on the unit scene (a glossy sphere); writes ``bench.json``."""
    os.makedirs(out, exist_ok=True)
    runs = [run_benchmark(name, out, quick) for name in tqdm(benchmarks.NAMES, desc="benchmarks",
                                                              disable=not progress, file=sys.stderr)]
    settings = {"res": res, "sampler": sampler, "envmap": None, "max_depth": 2}
    sweep = error_time_sweep(out, builtin.unit_scene_path(), settings, max_spp, ref_spp,
                             cache_dir, progress)
    summary = {"benchmarks": runs, "sweep": sweep}
    with open(os.path.join(out, "bench.json"), "w") as f:
        json.dump(summary, f, indent=2)
    return summary
