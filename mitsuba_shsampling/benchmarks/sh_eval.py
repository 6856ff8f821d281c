"""Throughput of the SH basis evaluation per band count.

Times :func:`mitsuba_shsampling.sh_eval` for l_max = 1..31 on random unit
directions (warm: the kernel is compiled by an untimed first run), and
``drjit.sh_eval`` in the same run where it exists (l_max <= 9). Each timing
covers trace + ``dr.eval`` of all (l_max+1)^2 outputs + ``dr.sync_thread``;
the median of several runs is reported.

    python3 scripts/bench_sh_eval.py [--quick] [--json OUT.json]
"""

from __future__ import annotations

import argparse
import statistics
import time

import drjit as dr
import mitsuba as mi

from ..sh.basis import sh_eval
from . import set_default_variant, write_json

DRJIT_MAX_ORDER = 9


def random_directions(count: int, seed: int) -> mi.Vector3f:
    sampler = mi.PCG32(size=count, initstate=seed)
    return mi.warp.square_to_uniform_sphere(
        mi.Point2f(sampler.next_float32(), sampler.next_float32()))


def time_eval(fn, d: mi.Vector3f, order: int, runs: int) -> float:
    """Median wall time (s) of evaluating all basis functions; first run untimed."""
    times = []
    for i in range(runs + 1):
        dr.sync_thread()
        start = time.perf_counter()
        dr.eval(fn(d, order))
        dr.sync_thread()
        if i > 0:
            times.append(time.perf_counter() - start)
    return statistics.median(times)


def run(quick: bool = False, runs: int | None = None) -> list[dict]:
    """One record per l_max: our and Dr.Jit's directions per second."""
    count = 1 << 20
    orders = [1, 3, 5, 9, 15, 19, 31] if quick else list(range(1, 32))
    runs = runs or (3 if quick else 5)
    d = random_directions(count, seed=1)
    dr.eval(d)

    records = []
    print(f"{'l_max':>5} {'bands':>5} {'coeffs':>6} {'ours M dir/s':>13} {'ours G val/s':>13}"
          f" {'drjit M dir/s':>14} {'ours/drjit':>10}")
    for order in orders:
        n_coeffs = (order + 1) ** 2
        ours = time_eval(sh_eval, d, order, runs)
        theirs = time_eval(dr.sh_eval, d, order, runs) if order <= DRJIT_MAX_ORDER else None
        record = {
            "l_max": order, "bands": order + 1, "coefficients": n_coeffs, "directions": count,
            "runs": runs, "ours_s": ours, "ours_mdir_per_s": count / ours / 1e6,
            "drjit_s": theirs, "drjit_mdir_per_s": None if theirs is None else count / theirs / 1e6,
        }
        records.append(record)
        ratio = "" if theirs is None else f"{theirs / ours:10.2f}"
        drjit_col = "" if theirs is None else f"{record['drjit_mdir_per_s']:14.1f}"
        print(f"{order:5d} {order + 1:5d} {n_coeffs:6d} {record['ours_mdir_per_s']:13.1f}"
              f" {count * n_coeffs / ours / 1e9:13.2f} {drjit_col:>14} {ratio:>10}", flush=True)
    return records


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--quick", action="store_true", help="fewer orders and runs (< 1 min)")
    parser.add_argument("--json", metavar="OUT.json", help="write the records as a JSON list")
    parser.add_argument("--runs", type=int, default=None, help="timed runs per measurement")
    args = parser.parse_args(argv)
    set_default_variant()
    records = run(args.quick, args.runs)
    if args.json:
        write_json(args.json, records)


if __name__ == "__main__":
    main()
