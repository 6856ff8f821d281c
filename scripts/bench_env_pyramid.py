"""Command-line entry point of :mod:`mitsuba_shsampling.benchmarks.env_pyramid` (options: ``--help``)."""

from mitsuba_shsampling.benchmarks.env_pyramid import main

if __name__ == "__main__":
    main()
