"""Build time and memory of EnvPyramid for synthetic sun-and-sky maps.

Each size is measured in a fresh Python process so that peak-memory figures
are not polluted by earlier runs. Prints a table and writes JSON.

    python3 scripts/bench_env_pyramid.py [--quick] [--sizes 512x1024 4096x8192] [--out env_pyramid_bench.json]

Columns: texels (H x W), depth D, build time (median of ``--repeats`` builds
after one warm-up), pyramid buffer size, and growth of the process's peak RSS
during the first build (the host arrays of Dr.Jit's kernels and numpy's
temporaries, and the emitter's own texel copy being read). No ``tracemalloc``:
under CPython 3.11 its allocator hook crashed the child at exit (a native thread
that Dr.Jit's exit handler starts asked for a thread state inside the hook; a core
dump's backtrace, 2026-12-07), about one run in five with another process busy.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys

from ..build_cache import ENVIRONMENT_VARIABLE
from . import write_json

SIZES = ("512x1024", "4096x8192")
QUICK_SIZES = ("512x1024",)


def measure_here(height: int, width: int, repeats: int) -> dict:
    """Build pyramids of one map size in this process; its peak figures are only
    meaningful in a fresh process (see :func:`measure`)."""
    import resource
    import statistics

    import mitsuba as mi

    mi.set_variant("llvm_ad_rgb")
    from ..envmap import EnvPyramid
    from ..envmap.synthetic import envmap_emitter, sun_sky_latlong

    emitter = envmap_emitter(sun_sky_latlong(height, width))
    rss_before = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    first = EnvPyramid(emitter)
    rss_growth = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss - rss_before
    times = [first.build_time_s] + [_rebuilt(emitter).build_time_s for _ in range(repeats)]
    return dict(height=height, width=width, depth=first.depth, first_build_s=times[0],
                build_s=statistics.median(times[1:] or times), buffer_mb=first.nbytes / 2**20,
                rss_growth_mb=rss_growth / 1024, total=first.total)


def _rebuilt(emitter) -> "EnvPyramid":
    """A pyramid built again, not the record the first build left in the process (in
    :func:`measure`'s child, whose disk cache is off, so that none is read from it either)."""
    from ..build_cache import clear_in_process
    from ..envmap import EnvPyramid

    clear_in_process()
    return EnvPyramid(emitter)


def measure(height: int, width: int, repeats: int) -> dict:
    """:func:`measure_here` in a fresh interpreter, with the disk cache of builds off: a
    build it held would be read, not built."""
    code = ("import json, sys; from mitsuba_shsampling.benchmarks.env_pyramid import measure_here; "
            "print(json.dumps(measure_here(*map(int, sys.argv[1:]))))")
    result = subprocess.run([sys.executable, "-X", "faulthandler", "-c", code, str(height), str(width),
                             str(repeats)], capture_output=True, text=True,
                            env=dict(os.environ, **{ENVIRONMENT_VARIABLE: "off"}))
    if result.returncode != 0:  # the child's own traceback (or fault handler's stacks) says why
        raise RuntimeError(f"measuring a {height}x{width} map failed (exit {result.returncode}):\n"
                           f"{result.stderr[-4000:]}")
    return json.loads(result.stdout.strip().splitlines()[-1])


def run(quick: bool = False, sizes: list[str] | None = None, repeats: int = 3) -> list[dict]:
    """One record per map size (``HEIGHTxWIDTH``)."""
    print(f"{'texels':>11} {'D':>3} {'first s':>8} {'build s':>8} {'buffer MB':>10} "
          f"{'RSS growth MB':>14}")
    rows = []
    for size in sizes or (QUICK_SIZES if quick else SIZES):
        height, width = map(int, size.lower().split("x"))
        r = measure(height, width, repeats)
        rows.append(r)
        print(f"{r['height']:>5}x{r['width']:<5} {r['depth']:>3} {r['first_build_s']:>8.3f} {r['build_s']:>8.3f} "
              f"{r['buffer_mb']:>10.1f} {r['rss_growth_mb']:>14.1f}", flush=True)
    return rows


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help=f"only {QUICK_SIZES[0]}")
    parser.add_argument("--sizes", nargs="+", help=f"map sizes as HEIGHTxWIDTH (default {' '.join(SIZES)})")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--out", "--json", dest="json", default="env_pyramid_bench.json")
    args = parser.parse_args(argv)
    write_json(args.json, run(args.quick, args.sizes, args.repeats))


if __name__ == "__main__":
    main()
