"""Throughput of a 2x2 split of SH cell integrals (the inner step of HSW).

For N random cells and one random SH expansion, computes the four child
integrals of every cell in two ways:

* ``separable``: three z antiderivative tables (z0, zmid, z1), one
  ``contract_z`` per z-half, two ``phi_integrals`` and four ``contract_phi``
  (about 2 n^2 + 8 n multiply-adds per split);
* ``per_child``: four independent ``function_cell_integral`` calls.

Prints a table and writes JSON. Timings exclude kernel compilation (one
warm-up run per configuration).

    python3 scripts/bench_cell_integrals.py [--quick] [--lanes 262144] [--repeats 5] [--json out.json]
"""

from __future__ import annotations

import argparse
import math
import time

import drjit as dr
import mitsuba as mi
import numpy as np

from ..sh.integrals import (contract_phi, contract_z, function_cell_integral, legendre_antiderivatives,
                            phi_integrals, z_integrals)
from . import set_default_variant, write_json


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
    for run_index in range(repeats + 1):  # run 0 compiles the kernel
        dr.sync_thread()
        start = time.perf_counter()
        out = split(coeffs, z0, z1, phi0, phi1, order)
        dr.eval(out)
        dr.sync_thread()
        if run_index:
            times.append(time.perf_counter() - start)
    return float(np.median(times))


def run(quick: bool = False, lanes: int | None = None, repeats: int | None = None,
        bands: list[int] | None = None) -> dict:
    """Both split methods at each band count; ``{"variant", "results": [...]}``."""
    lanes = lanes or (1 << 16 if quick else 1 << 18)
    repeats = repeats or (3 if quick else 5)
    bands = bands or ([5, 10] if quick else [5, 10, 20])
    rng = np.random.default_rng(1)
    results = []
    print(f"{'bands':>5} {'method':>10} {'ms':>9} {'Msplits/s':>10}")
    for n in bands:
        for name, split in (("separable", split_separable), ("per_child", split_per_child)):
            seconds = time_split(split, n, lanes, repeats, rng)
            results.append(dict(bands=n, method=name, lanes=lanes, seconds=seconds,
                                splits_per_second=lanes / seconds))
            print(f"{n:>5} {name:>10} {seconds * 1e3:9.2f} {lanes / seconds / 1e6:10.2f}", flush=True)
    return dict(variant=mi.variant(), results=results)


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--quick", action="store_true", help="2^16 lanes, 5 and 10 bands (< 1 min)")
    parser.add_argument("--lanes", type=int, help="cells per call (default 2^18, quick 2^16)")
    parser.add_argument("--repeats", type=int, help="timed runs (median; default 5, quick 3)")
    parser.add_argument("--bands", type=int, nargs="+", help="band counts (default 5 10 20)")
    parser.add_argument("--json", default="bench_cell_integrals.json")
    args = parser.parse_args(argv)
    set_default_variant()
    write_json(args.json, run(args.quick, args.lanes, args.repeats, args.bands))


if __name__ == "__main__":
    main()
