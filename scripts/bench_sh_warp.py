"""Command-line entry point of :mod:`mitsuba_shsampling.benchmarks.sh_warp` (options: ``--help``)."""

from mitsuba_shsampling.benchmarks.sh_warp import main

if __name__ == "__main__":
    main()
