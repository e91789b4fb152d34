"""Monocular obstacle ranging for a drone companion computer.

``companion.core`` holds the pure estimation code (derived in docs/derivations/): camera model and frames,
Harris corners, NCC matching, tracks, triangulation and the inverse-depth EKFs.  It performs no
I/O and keeps no global state.  ``companion.io`` holds the thin file readers (TOML, OpenCV
calibration YAML).  The benchmarks live outside the package, in the repository's top-level
``bench/`` (``python -m bench``): the companion never imports the simulator.
"""

from importlib.metadata import PackageNotFoundError as _NotInstalled, version as _dist_version

DISTRIBUTION = "monorange"  # the name pyproject.toml installs both packages (companion, flightsim) under


def package_version() -> str:
    """The installed distribution's version (``importlib.metadata``), or ``"unknown"`` when the source
    tree runs without being installed (``pip install -e .`` fixes that)."""
    try:
        return _dist_version(DISTRIBUTION)
    except _NotInstalled:
        return "unknown"


__version__ = package_version()
