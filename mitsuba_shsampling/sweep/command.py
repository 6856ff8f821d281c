"""``mitsuba-shsampling sweep GRID.toml --out DIR [--scheduler ADDRESS] [--workers N]``.

Exit codes as for ``compare``: 0 every cell finished, 2 bad input (grid file), 1 any cell
failed (the aggregate report is written all the same) or any other failure.
"""

from __future__ import annotations

import argparse
import os


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """The ``sweep`` subcommand's options."""
    parser.add_argument("grid", metavar="GRID.toml", help="grid file (see docs/SWEEP.md)")
    parser.add_argument("--out", default="sweep", help="output folder (default %(default)s)")
    parser.add_argument("--scheduler", metavar="ADDRESS",
                        help="address of a running Dask scheduler, e.g. tcp://host:8786 "
                             "(default: an embedded LocalCluster on this machine)")
    parser.add_argument("--workers", type=int, default=None,
                        help="LocalCluster worker processes (default: one per 2 cores, as each needs 2 Dr.Jit threads); with "
                             "--scheduler, the workers to wait for before starting")
    parser.add_argument("--cache-dir", default=None,
                        help="reference cache on the workers (default: compare's, on each worker)")
    parser.add_argument("--no-progress", action="store_true", help="hide the progress bar")


def command(args: argparse.Namespace) -> int:
    """Run the sweep of ``args``; prints one line per failed cell and the report's path."""
    from ..command_line import UsageError
    from .grid import GridError, load_grid

    if args.workers is not None and args.workers < 1:
        raise UsageError("--workers must be at least 1")
    try:
        grid = load_grid(args.grid)
    except GridError as err:
        raise UsageError(str(err)) from None
    from .run import run_sweep

    summary = run_sweep(grid, args.out, scheduler=args.scheduler, workers=args.workers,
                        cache_dir=args.cache_dir, progress=not args.no_progress)
    print(f"{len(summary.computed)} cells computed, {len(summary.reused)} reused, "
          f"{len(summary.failed)} failed")
    for label, error in summary.failed.items():
        print(f"failed: {label}: {error}")
    print(f"report: {os.path.abspath(summary.index_html)}")
    return 1 if summary.failed else 0
