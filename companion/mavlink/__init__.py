"""MAVLink I/O of the companion (docs/derivations/sectors.md).  Import :mod:`companion.mavlink.dialect` first."""
