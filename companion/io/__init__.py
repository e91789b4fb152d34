"""Thin I/O around the pure core: configuration and calibration files (:mod:`.config_files`),
input-file checks (:mod:`.inputs`), tlog reading with truncation checks (:mod:`.tlog`) and outputs
that appear complete or not at all (:mod:`.atomic`)."""
