"""flightsim.score (being split into a package: the next commit divides evaluation.py by concern; files.py was score_io.py)."""
