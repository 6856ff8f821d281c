"""Command-line entry point of :mod:`mitsuba_shsampling.benchmarks.product` (options: ``--help``)."""

from mitsuba_shsampling.benchmarks.product import main

if __name__ == "__main__":
    main()
