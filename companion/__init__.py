"""Monocular obstacle ranging for a drone companion computer.

``companion.core`` holds the pure estimation code (derived in docs/derivations/): camera model and frames,
Harris corners, NCC matching, tracks, triangulation and the inverse-depth EKFs.  It performs no
I/O and keeps no global state.  ``companion.io`` holds the thin file readers (TOML, OpenCV
calibration YAML).  The benchmarks live outside the package, in the repository's top-level
``bench/`` (``python -m bench``): the companion never imports the simulator.
"""

__version__ = "0.1.0"
