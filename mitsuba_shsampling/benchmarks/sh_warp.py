"""Throughput and pdf fidelity of the SH hierarchical sample warps.

Each of 2^20 lanes (``--lanes``) carries its own Phong lobe (exponent
``--exponent``, default 20) turned to a random axis; its SH coefficients are
computed in the same kernel as the warp (as a renderer would do per shading
point), so the figures include that cost; the coefficients alone (summed per
lane, so that n^2 floats per lane are not written out) are timed too, to tell
the warp's share. Timings are warm (the kernel is
compiled and run once first) and the best of ``--repeats`` runs with fresh
random inputs. Mitsuba's own ``envmap`` ``sample_direction`` (on the built-in
sun-and-sky map) is timed in the same process as a yardstick.

Fidelity: mean relative error |pdf - g| / g over sampled directions, with g
the exact normalised max(f, 0) of the (band-limited) SH lobe.

    python3 scripts/bench_sh_warp.py --quick --json OUT.json   # < 1 min
    python3 scripts/bench_sh_warp.py --json OUT.json           # full sweep

The machine is shared: the 1-minute load average is recorded with each row.
"""

from __future__ import annotations

import argparse
import math
import os
import time

import drjit as dr
import mitsuba as mi
import numpy as np

from ..scenes import SUNSKY_MAP
from ..sh.basis import sh_eval_sum
from ..sh.zonal import phong_attenuation, zonal_profile, zonal_to_sh
from ..warp.hsw import SHWarp
from ..warp.strip_hsw import SHStripWarp
from . import set_default_variant, write_json

WARPS = {
    "quadtree": lambda depth, leaf: SHWarp(depth, leaf),
    "strip": lambda depth, leaf: SHStripWarp(depth, leaf),
}
FULL_SWEEP = [(w, leaf, n, d) for n in (3, 5, 10, 15, 20)
              for w, leaf, depths in (("quadtree", "uniform", (4, 6, 8)),
                                      ("strip", "uniform", (8, 10, 12)),
                                      ("strip", "bilinear", (6, 8, 10)),
                                      ("strip", "linear", (6, 9, 12)))
              for d in depths]
QUICK_SWEEP = [("strip", "uniform", 5, 6), ("strip", "uniform", 5, 12), ("strip", "linear", 5, 9),
               ("strip", "uniform", 20, 12), ("strip", "linear", 20, 9), ("quadtree", "uniform", 5, 6)]


def _random_inputs(lanes: int, seed: int):
    rng = mi.PCG32(lanes, dr.opaque(mi.UInt64, seed))
    axis = mi.warp.square_to_uniform_sphere(mi.Point2f(rng.next_float32(), rng.next_float32()))
    u = mi.Point2f(rng.next_float32(), rng.next_float32())
    dr.eval(axis, u)
    return axis, u


def _best_time(run_once, lanes: int, repeats: int) -> float:
    best = math.inf
    for i in range(repeats + 1):  # run 0 compiles the kernel
        inputs = _random_inputs(lanes, seed=1000 + i)
        dr.sync_thread()
        start = time.perf_counter()
        dr.eval(run_once(*inputs))
        dr.sync_thread()
        if i > 0:
            best = min(best, time.perf_counter() - start)
    return best


def _positive_mass(attenuation) -> float:
    """Integral of max(f, 0) of the zonal lobe over the sphere (float64)."""
    t, w = np.polynomial.legendre.leggauss(64)
    edges = np.linspace(-1.0, 1.0, 257)
    mid, half = 0.5 * (edges[1:] + edges[:-1]), 0.5 * np.diff(edges)
    x = (mid[:, None] + half[:, None] * t[None, :]).ravel()
    weights = (half[:, None] * w[None, :]).ravel()
    return 2.0 * math.pi * float(np.sum(weights * np.maximum(zonal_profile(attenuation, x), 0.0)))


def measure(warp_name: str, leaf: str, n_bands: int, depth: int, exponent: float,
            lanes: int, repeats: int) -> dict:
    warp = WARPS[warp_name](depth, leaf)
    attenuation = phong_attenuation(exponent, n_bands)

    def run_once(axis, u):
        return warp.sample(zonal_to_sh(attenuation, axis), u)

    seconds = _best_time(run_once, lanes, repeats)
    coefficient_seconds = _best_time(lambda axis, u: sum(zonal_to_sh(attenuation, axis)), lanes, repeats)

    # Fidelity on a quarter of the lanes (same kernel shape, extra evaluation).
    axis, u = _random_inputs(max(lanes // 4, 1), seed=7)
    coeffs = zonal_to_sh(attenuation, axis)
    d, pdf = warp.sample(coeffs, u)
    target = dr.maximum(sh_eval_sum(coeffs, d), 0.0) / _positive_mass(attenuation)
    t, p = target.numpy(), pdf.numpy()
    keep = t > 0
    return dict(warp=warp_name, leaf=leaf, bands=n_bands, coefficients=n_bands**2, depth=depth,
                exponent=exponent, lanes=lanes, seconds=seconds, msamples_per_s=lanes / seconds / 1e6,
                coefficients_msamples_per_s=lanes / coefficient_seconds / 1e6,
                mean_rel_pdf_error=float(np.mean(np.abs(p[keep] - t[keep]) / t[keep])),
                load_average=os.getloadavg()[0])


def envmap_throughput(lanes: int, repeats: int) -> float:
    """Mitsuba envmap sample_direction on the built-in sun-and-sky map, M samples/s."""
    emitter = mi.load_dict({"type": "envmap", "filename": SUNSKY_MAP})
    it = dr.zeros(mi.Interaction3f)

    def run_once(axis, u):
        ds, weight = emitter.sample_direction(it, u)
        return ds.d, ds.pdf, weight

    return lanes / _best_time(run_once, lanes, repeats) / 1e6


def run(quick: bool = False, lanes: int = 2**20, repeats: int | None = None,
        exponent: float = 20.0) -> list[dict]:
    """One record per (warp, leaf, bands, depth) of the sweep."""
    repeats = repeats or (1 if quick else 3)
    envmap = envmap_throughput(lanes, repeats)
    rows = []
    print(f"{'warp':>9} {'leaf':>9} {'bands':>5} {'depth':>5} {'Msamples/s':>10} {'coeffs Ms/s':>11} "
          f"{'mean rel pdf err':>16} {'envmap Ms/s':>11} {'load':>5}")
    for warp_name, leaf, n_bands, depth in (QUICK_SWEEP if quick else FULL_SWEEP):
        r = measure(warp_name, leaf, n_bands, depth, exponent, lanes, repeats)
        r["mitsuba_envmap_msamples_per_s"] = envmap
        rows.append(r)
        print(f"{warp_name:>9} {leaf:>9} {n_bands:>5} {depth:>5} {r['msamples_per_s']:>10.2f} "
              f"{r['coefficients_msamples_per_s']:>11.1f} "
              f"{100 * r['mean_rel_pdf_error']:>15.3f}% {envmap:>11.1f} {r['load_average']:>5.1f}", flush=True)
    return rows


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="a few configurations (< 1 min)")
    parser.add_argument("--json", default="sh_warp_bench.json", help="output file (list of records)")
    parser.add_argument("--lanes", type=int, default=2**20)
    parser.add_argument("--repeats", type=int, default=None)
    parser.add_argument("--exponent", type=float, default=20.0, help="Phong exponent of the lobes")
    args = parser.parse_args(argv)
    set_default_variant()
    write_json(args.json, run(args.quick, args.lanes, args.repeats, args.exponent))


if __name__ == "__main__":
    main()
