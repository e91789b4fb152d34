"""MAVLink I/O of the companion (DESIGN.md §5).  Import :mod:`companion.mavlink.dialect` first."""
