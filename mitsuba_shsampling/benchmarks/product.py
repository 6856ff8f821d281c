"""Throughput and fidelity of ProductWarp (SH lobe x environment map).

For every map and band count: product sampling throughput (``sample``, which
returns direction and pdf, and ``pdf`` alone), Mitsuba's own
``envmap.sample_direction`` throughput measured right before it in the same
process, and the fidelity of the sampled distribution against the exact
normalised product (:func:`mitsuba_shsampling.fidelity.product_fidelity`,
averaged over a few fixed lobes). Prints a table and writes JSON.

    python3 scripts/bench_product.py [--quick] [--json OUT.json] [--envmap FILE.hdr ...]
                                     [--bands 3 5 10 15 20] [--sh-depths 2 4 6]

Maps: the ``--envmap`` files if given (the README's figures use the four Poly
Haven maps in ``tests/data/envmaps``), else the built-in sun-and-sky and
studio maps. Throughput lanes carry one Phong lobe each (random axis, exponent
s = n^2 / 5 for n bands, i.e. s = 20 at 10 bands), coefficients evaluated
beforehand and read from memory. Times are kernel execution times (Python's
tracing excluded, as a ``dr.freeze`` replay runs), the median of warm runs with
Mitsuba's sampler and the product's runs interleaved round by round (the first
call's wall time, compilation included, is reported separately); the operation
count of the traced kernels is reported as a load-independent cost. The ``lobe`` column
times the same sampling with the lobe built in the kernel from each lane's axis,
in the factored form the integrators pass
(:class:`~mitsuba_shsampling.sh.zonal.RotatedZonalLobes`), instead of n^2
coefficients read from memory: both over Mitsuba's sampler in the same run. With
``--sh-depths`` every listed sh_depth is measured (the trade-off table);
otherwise the default of each band count.

Memory per shading point: the n^2 float32 coefficients are the only
per-point data between kernels; the walk keeps about n(n+1)/2 + 2n + 16
further floats per lane in registers while it runs (the SH state of
:class:`~mitsuba_shsampling.warp.hsw.SHCellWeights`), freed afterwards.
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import statistics
import time
from typing import Callable

import drjit as dr
import mitsuba as mi
import numpy as np

from ..envmap import LEVEL_TOLERANCE, EnvPyramid
from ..fidelity import product_fidelity
from ..scenes import builtin_envmaps
from ..sh.zonal import RotatedZonalLobes, phong_attenuation, rotate_zonal_lobes
from ..warp.product import DEFAULT_PROXY_DEPTH, SH_DEPTH_WITH_PROXY, ProductWarp
from . import interleaved_kernel_seconds, set_default_variant, write_json

#: Lobe axes (grid frame) of the fidelity figures: zenith, horizon, nadir-ish, oblique.
#: Deepest pyramid on which the fidelity figures are computed (4^10 leaves).
FIDELITY_DEPTH = 10
FIDELITY_AXES = [(0.0, 0.0, 1.0), (1.0, 0.0, 0.0), (0.3, -0.5, -0.8), (-0.6, 0.6, 0.5)]


def phong_exponent(n_bands: int) -> float:
    """Phong exponent a band-n expansion represents reasonably (s = 20 at 10 bands)."""
    return n_bands * n_bands / 5.0


def phong_lobes(n_bands: int, axes: mi.Vector3f, s: float) -> list:
    """f_lm = lambda_l y_lm(axis) of the normalised Phong lobe, per lane."""
    return phong_lobes_factored(n_bands, axes, s).coefficients()


def phong_lobes_factored(n_bands: int, axes: mi.Vector3f, s: float) -> RotatedZonalLobes:
    """The same lobes in the factored form that the integrators pass to the warps."""
    return rotate_zonal_lobes([(phong_attenuation(s, n_bands), axes)])


def first_call_seconds(run) -> float:
    """Wall time (s) of ``run()``'s first call: tracing and compilation included."""
    start = time.perf_counter()
    run()
    return time.perf_counter() - start


def kernel_ops(run) -> int:
    """Operations in the kernels that ``run`` launches: a cost per sample that,
    unlike wall time, does not depend on the load of a shared machine."""
    dr.set_flag(dr.JitFlag.KernelHistory, True)
    dr.kernel_history()  # clear
    run()
    ops = sum(k.get("operation_count", 0) for k in dr.kernel_history() if k["type"] == dr.KernelType.JIT)
    dr.set_flag(dr.JitFlag.KernelHistory, False)
    return int(ops)


@dataclasses.dataclass(frozen=True)
class Settings:
    """What one run measures (see :func:`run` for the defaults)."""

    bands: tuple[int, ...]
    sh_depths: tuple[int, ...] | None
    lanes: int
    repeats: int
    fidelity_lobes: int
    proxy_depth: int = DEFAULT_PROXY_DEPTH
    """Proxy levels down to this depth (0: none, and the SH depth from the band count)."""
    level_tolerance: float = LEVEL_TOLERANCE
    """The pyramid's ``level_tolerance`` (0: every level the map's resolution asks for)."""

    def warp(self, pyramid, sh_depth: int | None) -> ProductWarp:
        """The warp measured at ``sh_depth`` (None: the default for these proxy levels)."""
        if sh_depth is None:
            sh_depth = SH_DEPTH_WITH_PROXY if self.proxy_depth else None
        return ProductWarp(pyramid, sh_depth=sh_depth, proxy_depth=self.proxy_depth or None)


def load_maps(files: list[str] | None) -> list[tuple[str, mi.Emitter]]:
    """(name, envmap emitter) of ``files``, or of the built-in maps."""
    paths = files or list(builtin_envmaps().values())
    return [(os.path.splitext(os.path.basename(f))[0],
             mi.load_dict({"type": "envmap", "filename": os.path.abspath(f)})) for f in paths]


def time_warp(warp, coeffs, factored: Callable, fresh_u, mitsuba_run, repeats: int) -> tuple:
    """``(compile_s, (mitsuba_s, sample_s, lobe_s, pdf_s), (sample_ops, lobe_ops, mitsuba_ops))``:
    the first sample call's wall time, then the median kernel times of Mitsuba's envmap sampling,
    the warp's sample from coefficients in memory (``coeffs``), from the lobe built in the kernel
    (``factored()``, traced into each run) and its pdf, and the operation counts of the three sampling kernels."""
    def sample_run():
        d, pdf = warp.sample(coeffs, fresh_u())
        dr.eval(d, pdf)
        dr.sync_thread()

    def sample_lobe_run():
        # As the integrators run it: the lobe built in the kernel from its axis (12 B a
        # lane read) in factored form (RotatedZonalLobes), not n^2 floats read from memory.
        d, pdf = warp.sample(factored(), fresh_u())
        dr.eval(d, pdf)
        dr.sync_thread()

    def pdf_run():
        d = mi.warp.square_to_uniform_sphere(fresh_u())
        dr.eval(d)
        dr.eval(warp.pdf(coeffs, d))
        dr.sync_thread()

    # Every run compiled once (that call's wall time reported), then timed interleaved
    # by kernel time: load on a shared machine drifts, and the ratio is what the
    # target is about.
    compile_s = first_call_seconds(sample_run)
    for warm in (mitsuba_run, sample_lobe_run, pdf_run):
        warm()
    times = interleaved_kernel_seconds(
        {"mitsuba": mitsuba_run, "sample": sample_run, "lobe": sample_lobe_run, "pdf": pdf_run}, repeats)
    medians = tuple(statistics.median(times[k]) for k in ("mitsuba", "sample", "lobe", "pdf"))
    return compile_s, medians, (kernel_ops(sample_run), kernel_ops(sample_lobe_run), kernel_ops(mitsuba_run))


def bench_map(name: str, emitter: mi.Emitter, settings: Settings) -> list[dict]:
    pyramid = EnvPyramid(emitter, level_tolerance=settings.level_tolerance)
    # Fidelity needs the pdf of every leaf: 4^12 = 17M at the default depth of
    # a 1k map. A pyramid capped at FIDELITY_DEPTH makes the same decisions in
    # the levels where the product's fidelity is lost (the coarse ones) and
    # keeps the figure affordable; its depth is recorded.
    fidelity_pyramid = (pyramid if pyramid.depth <= FIDELITY_DEPTH
                        else EnvPyramid(emitter, max_depth=FIDELITY_DEPTH))
    lanes = settings.lanes
    rng = np.random.default_rng(0)
    sampler = mi.PCG32(lanes)

    def fresh_u() -> mi.Point2f:
        u = mi.Point2f(sampler.next_float32(), sampler.next_float32())
        # Evaluate the generator's state too, or every call would trace a
        # longer chain of PCG steps into the next kernel.
        dr.eval(u, sampler.state)
        return u

    def mitsuba_run():
        ds, weight = emitter.sample_direction(dr.zeros(mi.Interaction3f, lanes), fresh_u())
        dr.eval(ds.d, ds.pdf, weight)
        dr.sync_thread()

    rows = []
    for n_bands in settings.bands:
        s = phong_exponent(n_bands)
        axes = mi.Vector3f(rng.normal(size=(3, lanes)).astype(np.float32))
        coeffs = phong_lobes(n_bands, axes, s)
        dr.eval(*coeffs)
        fidelity_lobes = [[float(c.numpy()[0]) for c in phong_lobes(n_bands, mi.Vector3f(*axis), s)]
                          for axis in FIDELITY_AXES[:settings.fidelity_lobes]]
        for sh_depth in (settings.sh_depths or [None]):
            warp = settings.warp(pyramid, sh_depth)
            compile_s, (mitsuba_s, sample_s, lobe_s, pdf_s), (sample_ops, lobe_ops, mitsuba_ops) = time_warp(
                warp, coeffs, lambda: phong_lobes_factored(n_bands, axes, s), fresh_u, mitsuba_run, settings.repeats)
            fidelity_warp = settings.warp(fidelity_pyramid, sh_depth)
            figures = [product_fidelity(fidelity_warp, lobe) for lobe in fidelity_lobes]
            mean = {key: float(np.mean([f[key] for f in figures])) for key in figures[0]}
            rows.append(dict(
                envmap=name, bands=n_bands, coefficients=n_bands * n_bands, phong_exponent=s,
                sh_depth=warp.sh_depth_for(n_bands), proxy_depth=settings.proxy_depth,
                depth=warp.depth, trimmed_levels=pyramid.trimmed_levels,
                level_tolerance=settings.level_tolerance, lanes=lanes,
                msamples_per_s=lanes / sample_s / 1e6,
                pdf_msamples_per_s=lanes / pdf_s / 1e6,
                mitsuba_envmap_msamples_per_s=lanes / mitsuba_s / 1e6,
                ratio_to_mitsuba=mitsuba_s / sample_s,
                lobe_in_kernel_msamples_per_s=lanes / lobe_s / 1e6,
                lobe_in_kernel_ratio_to_mitsuba=mitsuba_s / lobe_s,
                first_call_s=compile_s,
                sample_kernel_ops=sample_ops,
                lobe_in_kernel_ops=lobe_ops,
                mitsuba_kernel_ops=mitsuba_ops,
                product_fidelity=mean["mean_relative_error"],
                relative_variance=mean["relative_variance"],
                missed_mass=mean["missed_mass"],
                wasted_mass=mean["wasted_mass"],
                tail_mass=mean["tail_mass"],
                fidelity_lobes=len(figures),
                fidelity_depth=fidelity_warp.depth,
                coefficient_bytes_per_point=4 * n_bands * n_bands,
                walk_register_bytes_per_point=4 * (n_bands * (n_bands + 1) // 2 + 2 * n_bands + 16),
                pyramid_bytes=pyramid.nbytes))
            print(format_row(rows[-1]), flush=True)
    return rows


HEADER = (f"{'envmap':<28} {'bands':>5} {'D':>2} {'shd':>3} {'pxd':>3} {'M/s':>6} {'pdf M/s':>7} {'Mi M/s':>6} "
          f"{'ratio':>5} {'lobe':>5} {'ops':>6} {'Mi ops':>6} {'1st s':>5} {'fidelity':>8} {'rel.var':>7} {'missed':>7} {'wasted':>7} {'tail':>6} {'B/pt':>5}")


def format_row(r: dict) -> str:
    return (f"{r['envmap']:<28} {r['bands']:>5} {r['depth']:>2} {r['sh_depth']:>3} {r['proxy_depth']:>3} {r['msamples_per_s']:>6.2f} "
            f"{r['pdf_msamples_per_s']:>7.2f} {r['mitsuba_envmap_msamples_per_s']:>6.2f} "
            f"{r['ratio_to_mitsuba']:>5.2f} {r['lobe_in_kernel_ratio_to_mitsuba']:>5.2f} {r['sample_kernel_ops']:>6} {r['mitsuba_kernel_ops']:>6} {r['first_call_s']:>5.1f} {r['product_fidelity']:>8.4f} "
            f"{r['relative_variance']:>7.3f} {r['missed_mass']:>7.4f} {r['wasted_mass']:>7.4f} {r['tail_mass']:>6.3f} "
            f"{r['coefficient_bytes_per_point']:>5}")


def run(quick: bool = False, envmaps: list[str] | None = None, bands: list[int] | None = None,
        sh_depths: list[int] | None = None, lanes: int | None = None,
        repeats: int | None = None, proxy_depth: int = DEFAULT_PROXY_DEPTH,
        level_tolerance: float = LEVEL_TOLERANCE) -> list[dict]:
    """One record per (map, band count, sh_depth)."""
    settings = Settings(bands=tuple(bands or ([3, 10] if quick else [3, 5, 10, 15, 20])),
                        sh_depths=tuple(sh_depths) if sh_depths else None,
                        lanes=lanes or (1 << 18 if quick else 1 << 20),
                        repeats=repeats or (3 if quick else 5),
                        fidelity_lobes=1 if quick else len(FIDELITY_AXES),
                        proxy_depth=proxy_depth, level_tolerance=level_tolerance)
    print(HEADER, flush=True)
    rows = []
    for name, emitter in load_maps(envmaps):
        rows += bench_map(name, emitter, settings)
    return rows


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true",
                        help="2^18 lanes, bands 3 and 10, one fidelity lobe (< 1 minute)")
    parser.add_argument("--json", default="product_bench.json", help="output file")
    parser.add_argument("--envmap", nargs="+", help="maps to use instead of the built-in ones")
    parser.add_argument("--bands", type=int, nargs="+", help="band counts (default 3 5 10 15 20)")
    parser.add_argument("--sh-depths", type=int, nargs="+", help="sh_depth values to sweep")
    parser.add_argument("--proxy-depth", type=int, default=DEFAULT_PROXY_DEPTH,
                        help="proxy levels down to this depth (0: none, sh_depth from the band count)")
    parser.add_argument("--lanes", type=int, help="lanes per call (default 2^20, quick 2^18)")
    parser.add_argument("--repeats", type=int, help="warm runs per timing (median)")
    parser.add_argument("--level-tolerance", type=float, default=LEVEL_TOLERANCE,
                        help="the pyramid's level_tolerance (0: keep the levels finer than the texels)")
    args = parser.parse_args(argv)
    set_default_variant()
    write_json(args.json, run(args.quick, args.envmap, args.bands, args.sh_depths, args.lanes, args.repeats,
                              args.proxy_depth, args.level_tolerance))


if __name__ == "__main__":
    main()
