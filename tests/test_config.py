"""Configuration: the shipped TOML loads, every key is commented, bad keys are named."""

import re
from pathlib import Path

import numpy as np
import pytest

from companion.core.camera import CameraConfig
from companion.errors import ConfigError
from companion.io.config_files import CompanionConfig, load_companion_config, load_opencv_calibration

ROOT = Path(__file__).resolve().parents[1]
CONFIGS = sorted((ROOT / "configs").rglob("*.toml"))


def test_shipped_companion_config_loads():
    cfg = load_companion_config(ROOT / "configs" / "companion.toml")
    assert isinstance(cfg, CompanionConfig)
    assert cfg.harris.k == 0.04 and cfg.ncc.k_min == 0.8
    assert cfg.estimator.filter in ("anchored", "landmark")


@pytest.mark.parametrize("path", CONFIGS, ids=lambda p: p.name)
def test_every_key_has_a_comment(path):
    missing = []
    for n, line in enumerate(path.read_text(encoding="utf-8").splitlines(), 1):
        if re.match(r"^\s*[A-Za-z0-9_]+\s*=", line) and "#" not in line:
            missing.append(f"{path.name}:{n}: {line.strip()}")
    assert not missing, "keys without a comment:\n" + "\n".join(missing)


def test_shipped_config_covers_every_field():
    """The shipped file documents every key of every table (so users see all knobs)."""
    import dataclasses
    import tomllib

    data = tomllib.loads((ROOT / "configs" / "companion.toml").read_text())
    for table in dataclasses.fields(CompanionConfig):
        fields = {f.name for f in dataclasses.fields(type(getattr(CompanionConfig(), table.name)))}
        assert set(data[table.name]) == fields, f"[{table.name}] differs: {set(data[table.name]) ^ fields}"


def test_misspelt_key_is_named(tmp_path):
    p = tmp_path / "c.toml"
    p.write_text("[harris]\nkk = 0.05\n")
    with pytest.raises(ConfigError, match=r"\[harris\]: unknown key\(s\) 'kk'"):
        load_companion_config(p)
    p.write_text("[harrris]\nk = 0.05\n")
    with pytest.raises(ConfigError, match="top level: unknown key.*'harrris'"):
        load_companion_config(p)


def test_wrong_type_and_range_are_named(tmp_path):
    p = tmp_path / "c.toml"
    p.write_text('[camera]\nfx = "wide"\n')
    with pytest.raises(ConfigError, match=r"\[camera\] fx = 'wide' has the wrong type"):
        load_companion_config(p)
    p.write_text("[estimator]\nfilter = \"kalman\"\n")
    with pytest.raises(ConfigError, match=r"\[estimator\] filter must be one of"):
        load_companion_config(p)
    p.write_text("[camera\nfx = 1\n")
    with pytest.raises(ConfigError, match="not valid TOML"):
        load_companion_config(p)
    with pytest.raises(ConfigError, match="no such configuration file"):
        load_companion_config(tmp_path / "absent.toml")


def test_opencv_calibration_import(tmp_path):
    import cv2

    K = np.array([[612.5, 0, 331.2], [0, 611.9, 242.7], [0, 0, 1]])
    D = np.array([[-0.31, 0.11, 0.001, -0.0004, -0.02]])
    path = tmp_path / "calib.yaml"
    fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_WRITE)
    fs.write("image_width", 640)
    fs.write("image_height", 480)
    fs.write("camera_matrix", K)
    fs.write("distortion_coefficients", D)
    fs.release()
    base = CameraConfig(mount_rpy_deg=(0.0, -10.0, 0.0))
    cam = load_opencv_calibration(path, base=base)
    assert (cam.fx, cam.fy, cam.cx, cam.cy) == (612.5, 611.9, 331.2, 242.7)
    np.testing.assert_allclose(cam.distortion, D.ravel())
    assert cam.mount_rpy_deg == (0.0, -10.0, 0.0)
    bad = tmp_path / "bad.yaml"
    bad.write_text("%YAML:1.0\n---\nfoo: 1\n")
    with pytest.raises(ConfigError, match="camera_matrix"):
        load_opencv_calibration(bad)
