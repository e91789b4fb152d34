"""Packaging: ``--version`` on both command lines (from the installed metadata), the MIT LICENSE and
its PEP 639 declaration in pyproject.toml."""

from __future__ import annotations

import importlib.metadata
import re
import sys
from pathlib import Path

import pytest

from companion import DISTRIBUTION, package_version
from companion.cli import main as companion_main
from flightsim.cli import main as flightsim_main

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover - Python 3.10
    import tomli as tomllib

ROOT = Path(__file__).resolve().parents[1]


@pytest.mark.parametrize("main, prog", [(companion_main, "companion"), (flightsim_main, "flightsim")])
def test_version_flag_prints_the_installed_version_and_exits_0(main, prog, capsys):
    with pytest.raises(SystemExit) as e:
        main(["--version"])
    assert e.value.code == 0
    out = capsys.readouterr().out.strip()
    installed = importlib.metadata.version(DISTRIBUTION)
    assert out == f"{prog} {installed} ({DISTRIBUTION})"
    assert package_version() == installed


def test_installed_version_matches_pyproject():
    project = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]
    assert project["name"] == DISTRIBUTION
    assert importlib.metadata.version(DISTRIBUTION) == project["version"]


def test_license_file_and_spdx_declaration():
    text = (ROOT / "LICENSE").read_text()
    assert text.startswith("MIT License\n")
    assert "Copyright (c) 2026 The companion authors" in text
    assert "THE SOFTWARE IS PROVIDED \"AS IS\"" in text
    py = tomllib.loads((ROOT / "pyproject.toml").read_text())
    assert py["project"]["license"] == "MIT"  # an SPDX expression (PEP 639), not the deprecated table
    assert py["project"]["license-files"] == ["LICENSE"]
    assert not any(c.startswith("License ::") for c in py["project"].get("classifiers", []))  # PEP 639 forbids both
    # setuptools reads a string license and license-files from 77 on: the build backend must be new enough
    (setuptools_req,) = [r for r in py["build-system"]["requires"] if r.startswith("setuptools")]
    m = re.fullmatch(r"setuptools>=(\d+)(?:\.\d+)*", setuptools_req)
    assert m and int(m.group(1)) >= 77, setuptools_req


def test_systemd_unit_runs_the_companion_as_its_own_user_and_logs_to_journald():
    text = (ROOT / "deploy" / "companion.service").read_text()
    lines = {ln.strip() for ln in text.splitlines()}
    for want in ("[Unit]", "[Service]", "[Install]", "User=companion", "SupplementaryGroups=dialout video",
                 "Restart=on-failure", "RestartPreventExitStatus=2", "StandardOutput=journal", "StandardError=journal",
                 "WantedBy=multi-user.target"):
        assert want in lines, want
    exec_start = text.split("ExecStart=", 1)[1].split("\n#", 1)[0].replace("\\\n", " ")
    assert "/bin/companion run" in exec_start and "--mavlink" in exec_start and "--config" in exec_start
    # kernels compiled (or loaded) in a process of their own, into the cache the flight process reads
    assert "ExecStartPre=/opt/companion/.venv/bin/companion kernels" in lines
    assert "Environment=NUMBA_CACHE_DIR=/var/cache/companion" in lines and "CacheDirectory=companion" in lines
    readme = (ROOT / "README.md").read_text()
    section = readme.split("## Running on a Raspberry Pi or Jetson", 1)[1].split("\n## ", 1)[0]
    for want in ("SERIALn_PROTOCOL = 2", "MAV_1_CONFIG", "dialout", "video", "companion check", "journalctl -u companion",
                 "MAVLink 2", "deploy/companion.service"):
        assert want in section, want
