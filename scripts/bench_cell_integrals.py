"""Command-line entry point of :mod:`mitsuba_shsampling.benchmarks.cell_integrals` (options: ``--help``)."""

from mitsuba_shsampling.benchmarks.cell_integrals import main

if __name__ == "__main__":
    main()
