"""Build time and memory of EnvPyramid for synthetic sun-and-sky maps.

Each size runs in a fresh Python process so that peak-memory figures are not
polluted by earlier runs. Prints a table and writes JSON.

    python3 scripts/bench_env_pyramid.py [--sizes 512x1024 4096x8192] [--out env_pyramid_bench.json]

Columns: texels (H x W), depth D, build time (median of ``--repeats`` builds
after one warm-up), pyramid buffer size, peak numpy temporaries during the
build (tracemalloc), and growth of the process's peak RSS during the first
build (includes the emitter's own texel copy being read).
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys

WORKER = r"""
import json, resource, statistics, sys, time, tracemalloc
import mitsuba as mi
mi.set_variant('llvm_ad_rgb')
from mitsuba_shsampling.envmap import EnvPyramid
from mitsuba_shsampling.envmap.synthetic import envmap_emitter, sun_sky_latlong
height, width, repeats = map(int, sys.argv[1:4])
emitter = envmap_emitter(sun_sky_latlong(height, width))
rss_before = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
tracemalloc.start()
first = EnvPyramid(emitter)
numpy_peak = tracemalloc.get_traced_memory()[1]
tracemalloc.stop()
rss_growth = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss - rss_before
times = [first.build_time_s]
for _ in range(repeats):
    times.append(EnvPyramid(emitter).build_time_s)
print(json.dumps(dict(height=height, width=width, depth=first.depth,
                      first_build_s=times[0], build_s=statistics.median(times[1:] or times),
                      buffer_mb=first.nbytes / 2**20, numpy_peak_mb=numpy_peak / 2**20,
                      rss_growth_mb=rss_growth / 1024, total=first.total)))
"""


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sizes", nargs="+", default=["512x1024", "4096x8192"],
                        help="map sizes as HEIGHTxWIDTH")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--out", default="env_pyramid_bench.json")
    args = parser.parse_args()

    rows = []
    for size in args.sizes:
        height, width = map(int, size.lower().split("x"))
        result = subprocess.run([sys.executable, "-c", WORKER, str(height), str(width), str(args.repeats)],
                                check=True, capture_output=True, text=True)
        rows.append(json.loads(result.stdout.strip().splitlines()[-1]))

    header = f"{'texels':>11} {'D':>3} {'first s':>8} {'build s':>8} {'buffer MB':>10} {'numpy peak MB':>14} {'RSS growth MB':>14}"
    print(header)
    for r in rows:
        print(f"{r['height']:>5}x{r['width']:<5} {r['depth']:>3} {r['first_build_s']:>8.3f} {r['build_s']:>8.3f} "
              f"{r['buffer_mb']:>10.1f} {r['numpy_peak_mb']:>14.1f} {r['rss_growth_mb']:>14.1f}")
    with open(args.out, "w") as f:
        json.dump(rows, f, indent=2)
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
