"""Pure estimation core (derived in docs/derivations/): no I/O, no globals; every function takes arrays in and gives arrays out."""
