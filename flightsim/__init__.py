"""flightsim: JSBSim flights that prove the companion."""
