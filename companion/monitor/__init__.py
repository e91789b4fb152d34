"""``companion monitor`` (being split into a package: the next commit divides state.py into decode / state / view / runner)."""
