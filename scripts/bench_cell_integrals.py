"""Throughput of a 2x2 split of SH cell integrals (the inner step of HSW).

For N random cells and one random SH expansion, computes the four child
integrals of every cell in two ways:

* ``separable``: three z antiderivative tables (z0, zmid, z1), one
  ``contract_z`` per z-half, two ``phi_integrals`` and four ``contract_phi``
  (about 2 n^2 + 8 n multiply-adds per split);
* ``per_child``: four independent ``function_cell_integral`` calls.

Prints a table and writes JSON. Timings exclude kernel compilation (one
warm-up run per configuration).

    python3 scripts/bench_cell_integrals.py [--lanes 262144] [--repeats 5] [--json out.json]
"""

from __future__ import annotations

import argparse
import json
import math
import time

import mitsuba_shsampling  # noqa: F401  (picks a good libLLVM before drjit loads)
import drjit as dr
import mitsuba as mi
import numpy as np

mi.set_variant("llvm_ad_rgb")

from mitsuba_shsampling.sh.integrals import (  # noqa: E402
    contract_phi, contract_z, function_cell_integral, legendre_antiderivatives,
    phi_integrals, z_integrals)


def split_separable(coeffs, z0, z1, phi0, phi1, order):
    """Four child integrals, ordered (a, b) = (0,0), (0,1), (1,0), (1,1)."""
    zm, pm = 0.5 * (z0 + z1), 0.5 * (phi0 + phi1)
    f0, fm, f1 = (legendre_antiderivatives(z, order) for z in (z0, zm, z1))
    rows = [contract_z(coeffs, z_integrals(lo, hi), order) for lo, hi in ((f0, fm), (fm, f1))]
    cols = [phi_integrals(a, b, order) for a, b in ((phi0, pm), (pm, phi1))]
    return [contract_phi(r, c) for r in rows for c in cols]


def split_per_child(coeffs, z0, z1, phi0, phi1, order):
    zm, pm = 0.5 * (z0 + z1), 0.5 * (phi0 + phi1)
    return [function_cell_integral(coeffs, za, zb, pa, pb)
            for za, zb in ((z0, zm), (zm, z1)) for pa, pb in ((phi0, pm), (pm, phi1))]


def time_split(split, bands: int, lanes: int, repeats: int, rng) -> float:
    """Median seconds per evaluation of ``split`` over ``lanes`` cells."""
    order = bands - 1
    coeffs = [mi.Float(c) for c in rng.normal(size=bands * bands)]
    depth = 8
    iz = rng.integers(0, 2 ** depth, lanes)
    ip = rng.integers(0, 2 ** depth, lanes)
    z0 = mi.Float(-1 + 2 * iz / 2 ** depth)
    z1 = mi.Float(-1 + 2 * (iz + 1) / 2 ** depth)
    phi0 = mi.Float(2 * math.pi * ip / 2 ** depth)
    phi1 = mi.Float(2 * math.pi * (ip + 1) / 2 ** depth)
    times = []
    for run in range(repeats + 1):  # run 0 compiles the kernel
        dr.sync_thread()
        start = time.perf_counter()
        out = split(coeffs, z0, z1, phi0, phi1, order)
        dr.eval(out)
        dr.sync_thread()
        if run:
            times.append(time.perf_counter() - start)
    return float(np.median(times))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--lanes", type=int, default=1 << 18)
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--bands", type=int, nargs="+", default=[5, 10, 20])
    parser.add_argument("--json", default="bench_cell_integrals.json")
    args = parser.parse_args()

    rng = np.random.default_rng(1)
    results = []
    print(f"{'bands':>5} {'method':>10} {'ms':>9} {'Msplits/s':>10}")
    for bands in args.bands:
        for name, split in (("separable", split_separable), ("per_child", split_per_child)):
            seconds = time_split(split, bands, args.lanes, args.repeats, rng)
            rate = args.lanes / seconds / 1e6
            results.append(dict(bands=bands, method=name, lanes=args.lanes,
                                seconds=seconds, splits_per_second=args.lanes / seconds))
            print(f"{bands:>5} {name:>10} {seconds * 1e3:9.2f} {rate:10.2f}")
    with open(args.json, "w") as f:
        json.dump(dict(variant=mi.variant(), results=results), f, indent=2)
    print(f"wrote {args.json}")


if __name__ == "__main__":
    main()
