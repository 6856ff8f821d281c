"""Command-line entry point of :mod:`mitsuba_shsampling.benchmarks.lobes` (options: ``--help``)."""

from mitsuba_shsampling.benchmarks.lobes import main

if __name__ == "__main__":
    main()
