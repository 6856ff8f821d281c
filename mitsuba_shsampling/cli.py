"""Command line: ``mitsuba-shsampling compare|bench|render|sweep|calibrate`` (also ``python -m mitsuba_shsampling``).

Exit codes: 0 success, 2 bad input (missing scene or map, unknown method or
variant, invalid option), 1 any other failure.
"""

from __future__ import annotations

import argparse
import math
import os
import sys
from typing import TYPE_CHECKING

from . import calibration, render
from .command_line import (DEFAULT_VARIANT, SAMPLERS, UsageError, check_output_folder, max_depth_problem,
                           set_variant)
from .sweep import command as sweep
from .report import DEFAULT_CACHE_DIR
from .report.schema import CONTEST_TITLES, CompareSettings

if TYPE_CHECKING:
    from .report.schema import Report, VerdictRow

COMPARE_RES = CompareSettings.res


def _positive(text: str) -> int:
    value = int(text)
    if value < 1:
        raise argparse.ArgumentTypeError(f"expected a positive integer, got {text}")
    return value


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="mitsuba-shsampling",
                                     description="SH product sampling for Mitsuba 3: comparisons and benchmarks")
    sub = parser.add_subparsers(dest="command", required=True)

    common = argparse.ArgumentParser(add_help=False)
    common.add_argument("--variant", default=DEFAULT_VARIANT, help="Mitsuba JIT variant (default %(default)s)")
    common.add_argument("--res", type=_positive, default=128,
                        help=f"image width in pixels, the height following the scene's aspect "
                             f"(default: {COMPARE_RES} for compare, %(default)s otherwise)")
    common.add_argument("--ref-spp", type=_positive, default=1024, help="reference spp (default %(default)s)")
    common.add_argument("--cache-dir", default=DEFAULT_CACHE_DIR, help="reference cache (default %(default)s)")
    common.add_argument("--no-progress", action="store_true", help="hide progress bars")

    compare = sub.add_parser("compare", parents=[common],
                             help="render every method at equal samples and equal time, write a report")
    # 256 px wide: at 192 the material studio's film variance under its sun-and-sky map
    # was 83 % pixel-footprint variance that no light sampler changes (the chooser's
    # shared variance) and the verdict's equal-time interval spanned 0.76-1.06; at 256
    # that share is 68 % and the interval 0.97-1.04 (README, "The default job"). The
    # job stays near two minutes on 2 cores.
    compare.set_defaults(res=COMPARE_RES)
    compare.add_argument("scenes", nargs="*", metavar="SCENE.xml",
                         help="Mitsuba 3 scene files, used as written (their camera is rebuilt at --res "
                              "with each --sampler; default: the built-in material_studio scene)")
    compare.add_argument("--out", default="report", help="report folder (default %(default)s)")
    compare.add_argument("--spp", type=_positive, default=8, help="samples per pixel at 2 rays each (default %(default)s)")
    compare.add_argument("--passes", type=int, default=32,
                         help="independent passes per method and comparison, >= 2; many low-spp passes "
                              "let rare, huge samples into the expected error (default %(default)s)")
    compare.add_argument("--envmap", help="lat-long map replacing the scene's envmap emitter")
    compare.add_argument("--methods", help="comma-separated method names (default: all available)")
    compare.add_argument("--sampler", default="independent",
                         help=f"comma-separated samplers among {', '.join(SAMPLERS)} (default %(default)s)")
    compare.add_argument("--seed", type=int, default=0, help="seed of the first pass (default %(default)s)")
    compare.add_argument("--max-depth", type=int, default=2,
                         help="Mitsuba's max_depth: 2 is direct lighting; above 2, or -1 (infinite), adds the "
                              "multi-bounce methods path and sh_path at that depth (default %(default)s)")
    compare.add_argument("--convergence-max-spp", type=int, default=None,
                         help="largest spp of the convergence sweep (default 4 x spp, 0 disables)")
    compare.add_argument("--no-freeze", action="store_true",
                         help="trace every pass instead of replaying a dr.freeze recording of it (the "
                              "pass times then include Python's tracing)")

    bench = sub.add_parser("bench", parents=[common], help="run the sampler benchmarks and an error-vs-time sweep")
    bench.add_argument("--out", default="bench", help="output folder (default %(default)s)")
    bench.add_argument("--quick", action="store_true", help="about a minute per benchmark; smaller sweep")
    bench.add_argument("--sampler", default="independent", choices=SAMPLERS)
    bench.add_argument("--max-spp", type=_positive, default=None, help="largest spp of the sweep (default 256, quick 16)")

    render.add_parser(sub, DEFAULT_VARIANT)
    calibration.add_parser(sub, DEFAULT_VARIANT)
    sweep.add_arguments(sub.add_parser("sweep", help="run compare over a grid of scenes x maps x samplers (Dask)"))
    return parser


def _split(text: str | None) -> list[str] | None:
    return [t.strip() for t in text.split(",") if t.strip()] if text else None


def _compare(args) -> int:
    for path in args.scenes:
        if not os.path.isfile(path):
            raise UsageError(f"scene file not found: {path}")
    if args.envmap and not os.path.isfile(args.envmap):
        raise UsageError(f"environment map not found: {args.envmap}")
    check_output_folder(args.out)
    if args.passes < 2:
        raise UsageError("--passes must be at least 2 (variance and bias need several passes)")
    if max_depth_problem(args.max_depth):
        raise UsageError(f"--max-depth {max_depth_problem(args.max_depth)}")
    if args.methods is not None and not _split(args.methods):
        raise UsageError("--methods names no method; leave it out to run every available method")
    samplers = _split(args.sampler) or []
    unknown = [s for s in samplers if s not in SAMPLERS]
    if unknown or not samplers:
        raise UsageError(f"unknown sampler(s) {', '.join(unknown) or '(none)'}; choose among {', '.join(SAMPLERS)}")
    set_variant(args.variant)

    from . import scenes
    from .report.compare import run_compare
    from .report.methods import method_by_name

    methods = _split(args.methods)
    for name in methods or []:
        try:
            method_by_name(name)
        except ValueError as err:
            raise UsageError(str(err)) from None
    paths = args.scenes or [scenes.default_scene_path()]
    settings = CompareSettings(out=args.out, res=args.res, spp=args.spp, passes=args.passes,
                               ref_spp=args.ref_spp, samplers=tuple(samplers),
                               methods=tuple(methods) if methods else None, envmap=args.envmap,
                               max_depth=args.max_depth, seed=args.seed,
                               convergence_max_spp=args.convergence_max_spp,
                               cache_dir=args.cache_dir, progress=not args.no_progress,
                               freeze=not args.no_freeze)
    report = run_compare(paths, settings)
    _print_summary(report)
    print(f"\nreport: {os.path.join(os.path.abspath(args.out), 'index.html')}")
    return 0


def _fmt(value, spec: str) -> str:
    """``value`` formatted by ``spec``; a missing or non-finite one as ``n/a`` of the same width."""
    if value is None or (isinstance(value, float) and not math.isfinite(value)):
        return "n/a".rjust(int(spec.split(".")[0] or 0))
    return format(value, spec)


def _print_summary(report: Report) -> None:
    """The verdict, then one line per method and comparison (n/a: see the report's notes)."""
    from .integrators.chooser import summary_of as strategy_summary

    for scene in report.scenes:
        for note in scene.notes:
            print(f"note ({scene.scene}): {note}")
        for run in scene.runs:
            print(f"\n{scene.scene} [{run.sampler}]")
            print(f"  {'method':<16}{'kind':<11}{'spp':>5}{'exp. MSE':>11}{'pix.var':>10}{'time(s)':>9}"
                  f"{'eff/base':>9}{'max px':>9}{'fireflies':>10}{'bias p':>9}")
            for name, entry in run.methods.items():
                for kind in ("equal_spp", "equal_time"):
                    e = getattr(entry, kind)
                    print(f"  {name:<16}{kind:<11}{e.spp:>5}{_fmt(e.error.mse, '11.3e')}"
                          f"{_fmt(e.error.pixel_variance, '10.2e')}{_fmt(e.time_s, '9.3f')}"
                          f"{_fmt(e.efficiency_ratio_vs_baseline, '9.2f')}{_fmt(e.tail.max_pixel, '9.3g')}"
                          f"{e.tail.fireflies:>10}{_fmt(e.bias.p_value, '9.2g')}"
                          f"{'  BIAS?' if e.bias.flagged else ''}"
                          f"{'  TAIL' if e.tail_worse_than_baseline else ''}")
            print("  before the first pass (s): " + ", ".join(
                f"{name} set-up {_fmt(entry.setup_time_s, '.2f').strip()} + compile "
                f"{_fmt(entry.compile_time_s, '.2f').strip()}" for name, entry in run.methods.items()))
            for name, entry in run.methods.items():
                if entry.strategy_choice:
                    print(f"  {name} strategy (auto): {strategy_summary(entry.strategy_choice)}")
            for family, rows in (run.materials or {}).items():
                project = list(rows[0].error_ratio) if rows else []
                print(f"  per material ({family}): pixels, squared error / best Mitsuba there at equal samples and "
                      f"equal time, share of the method's error")
                for row in rows:
                    cells = "  ".join(f"{n} {_fmt(row.error_ratio[n].get('equal_spp'), '.2f')} / "
                                      f"{_fmt(row.error_ratio[n].get('equal_time'), '.2f')} "
                                      f"({_fmt(row.error_share.get(n), '.0%')})" for n in project)
                    print(f"    {row.name[:22]:<23}{row.plugin[:16]:<17}{row.pixel_share:>6.1%}  "
                          f"vs {str(row.best_mitsuba.get('equal_spp')):<12}{cells}")
    print("\nverdict:")
    _print_verdict(report.verdict)


def _print_verdict(rows: list[VerdictRow]) -> None:
    """Each verdict row: every contest of its lines, then its caveats."""
    from .report.verdict import winner_text

    for row in rows:
        print(f"  {row.scene} [{row.sampler}, {row.family}]")
        for label, line in [(row.configuration, row)] + [(o.configuration, o) for o in row.others or []]:
            for kind, title in CONTEST_TITLES.items():
                c = getattr(line, kind)
                if c is None:
                    continue
                print(f"    {title}: {label or c.numerator} / {c.denominator} {c.quantity} "
                      f"x{_fmt(c.ratio, '.3g')} [{_fmt(c.low, '.3g')}, {_fmt(c.high, '.3g')}] "
                      f"({winner_text(c, kind, row.caveats)})")
        for caveat in row.caveats:
            print(f"    caveat: {caveat}")


def _bench(args) -> int:
    check_output_folder(args.out)
    set_variant(args.variant)
    from .report.bench import run_bench

    max_spp = args.max_spp or (16 if args.quick else 256)
    res = min(args.res, 64) if args.quick else args.res
    summary = run_bench(args.out, args.quick, res, args.sampler, max_spp, args.ref_spp,
                        args.cache_dir, progress=not args.no_progress)
    for run in summary["benchmarks"]:
        status = f"FAILED ({run['error']})" if run["error"] else f"JSON: {run['json']}"
        print(f"{run['benchmark']}: {run['time_s']:.1f} s, {status}")
    print(f"sweep: {os.path.join(os.path.abspath(args.out), 'sweep.json')}")
    return 0


def _user_error(err: BaseException) -> str | None:
    """The one-line message of a bad-input error anywhere in ``err``'s cause chain
    (``mi.render`` wraps errors raised while rendering), else None."""
    from ._backend import VariantError
    from .envmap.pyramid import EnvmapError
    from .integrators.options import OptionError
    from .scenes import SceneError

    while err is not None:
        if isinstance(err, (SceneError, EnvmapError, OptionError, VariantError, render.RenderError)):
            return str(err)
        err = err.__cause__ or err.__context__
    return None


def main(argv: list[str] | None = None) -> int:
    """Entry point of the ``mitsuba-shsampling`` console script; returns the exit code."""
    args = build_parser().parse_args(argv)
    commands = {"compare": _compare, "bench": _bench, "render": lambda a: render.main(a, set_variant),
                "sweep": sweep.command, "calibrate": lambda a: calibration.main(a, set_variant)}
    try:
        return commands[args.command](args)
    except UsageError as err:
        print(f"mitsuba-shsampling: error: {err}", file=sys.stderr)
        return 2
    except Exception as err:
        message = _user_error(err)
        if message is None:
            raise
        print(f"mitsuba-shsampling: error: {message}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
