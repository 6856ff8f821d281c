"""Command-line entry point of :mod:`mitsuba_shsampling.benchmarks.sh_eval` (options: ``--help``)."""

from mitsuba_shsampling.benchmarks.sh_eval import main

if __name__ == "__main__":
    main()
