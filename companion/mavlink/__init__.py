"""MAVLink I/O of the companion (docs/derivations/link.md).  Import :mod:`companion.mavlink.dialect` first."""
