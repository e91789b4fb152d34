"""Reproducible benchmarks (DESIGN.md §4): ``python -m companion.bench --help``."""
