"""Packaging that pyproject.toml cannot say statically: the repository's ``configs/`` directory is
shipped inside the wheel as ``companion/configs`` (one copy of each file; the companion finds it in
either place, see :func:`companion.io.config_files.shipped_config_dir`)."""

from setuptools import find_packages, setup

setup(
    packages=find_packages(include=["companion", "companion.*", "flightsim", "flightsim.*"]) + ["companion.configs", "companion.configs.scenarios", "companion.configs.worlds"],
    package_dir={"companion.configs": "configs"},
)
