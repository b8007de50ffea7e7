"""Offline planners, experiments, benchmarks and the ``implantplan`` command line."""
