"""Reproducible benchmarks (the source papers' scenarios, seeds 000 and 004): ``python -m bench --help``."""
