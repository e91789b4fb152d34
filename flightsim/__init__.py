"""flightsim: JSBSim flights that prove the companion (DESIGN.md §1)."""
