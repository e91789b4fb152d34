"""Thin I/O around the pure core: configuration files and camera calibration files."""
