"""Sampler benchmarks, importable (``scripts/bench_*.py`` are their command-line entry points).

Every module here has the same two functions:

- ``run(quick=False, **options) -> records``: measure, print a table while it
  goes, and return the records (a list of dicts, or a dict of them) as JSON
  data. ``quick=True`` finishes in about a minute on the project's 2-core machine.
- ``main(argv=None)``: the script: parse options, set the ``llvm_ad_rgb``
  variant, :func:`run`, write the records as JSON (``--json``).

:data:`NAMES` lists them; the ``bench`` command
(:mod:`mitsuba_shsampling.report.bench`) calls each ``run`` in turn. Timings are
warm (each kernel runs once before it is timed) and, on a shared machine, only
comparable within one run.
"""

from __future__ import annotations

import importlib
import json

#: Benchmark name -> module (``mitsuba_shsampling.benchmarks.<name>``), in run order.
NAMES = ("sh_eval", "cell_integrals", "sh_warp", "product", "env_pyramid", "lobes")


def benchmark(name: str):
    """The module of benchmark ``name`` (imported on first use: each sets up kernels)."""
    if name not in NAMES:
        raise ValueError(f"unknown benchmark '{name}' (known: {', '.join(NAMES)})")
    return importlib.import_module(f"{__name__}.{name}")


def write_json(path: str, records) -> None:
    """Write ``records`` to ``path`` and say so."""
    with open(path, "w") as f:
        json.dump(records, f, indent=1)
    print(f"wrote {path}")


def kernel_seconds(run) -> float:
    """Execution time (s) of the JIT kernels that ``run()`` launches (it must wait for them):
    what a replayed ``dr.freeze`` recording costs, without Python's tracing (the chooser's
    :func:`~mitsuba_shsampling.timing.kernel_time`)."""
    from ..timing import kernel_time

    return kernel_time(run)[1]


def interleaved_kernel_seconds(runs: dict, repeats: int) -> dict:
    """Name -> the kernel times (s) of ``repeats`` calls of each of ``runs`` (name ->
    callable), interleaved: round k calls every run once, starting with run k (mod their
    number), so a slow spell of a shared machine falls on all of them alike and none always
    follows the same one."""
    names = list(runs)
    times = {name: [] for name in names}
    for k in range(repeats):
        shift = k % len(names)
        for name in names[shift:] + names[:shift]:
            times[name].append(kernel_seconds(runs[name]))
    return times


def set_default_variant() -> None:
    """The variant the benchmarks measure (their scripts' only one)."""
    import mitsuba as mi

    mi.set_variant("llvm_ad_rgb")
