"""Pure estimation core (DESIGN.md §2–§3): no I/O, no globals; every function takes arrays in and gives arrays out."""
