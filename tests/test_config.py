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


# ------------------------------------------------------------------ shipped configuration, overlays
def _fields(cfg):
    import dataclasses

    return {(t.name, f.name): getattr(getattr(cfg, t.name), f.name)
            for t in dataclasses.fields(cfg) for f in dataclasses.fields(getattr(cfg, t.name))}


def test_no_config_means_the_shipped_file():
    from companion.cli import load_config
    from companion.io.config_files import shipped_config, shipped_config_dir

    assert shipped_config_dir() == ROOT / "configs"  # a source checkout: the repository's files (the wheel maps them in)
    assert shipped_config() == ROOT / "configs" / "companion.toml"
    shipped = load_companion_config(ROOT / "configs" / "companion.toml")
    assert load_companion_config() == shipped
    assert load_config(None).companion == shipped  # what `companion run/replay` use without --config


def _flat(obj, prefix=""):
    """Every leaf key of a config, ``"table.key"`` (nested tables too: ``"link.timesync.interval_s"``) → value."""
    import dataclasses

    if not dataclasses.is_dataclass(obj):
        return {prefix[:-1]: obj}
    out = {}
    for f in dataclasses.fields(obj):
        out.update(_flat(getattr(obj, f.name), f"{prefix}{f.name}."))
    return out


def test_built_in_defaults_are_the_shipped_configuration():
    """One source: the modules' dataclass defaults equal configs/companion.toml key by key, so the
    library (``CompanionConfig()``, a module's ``XConfig()``) behaves exactly like a command run
    without --config, and an edit to either side alone fails here naming the key."""
    from companion.cli import load_config

    shipped = _flat(load_companion_config(ROOT / "configs" / "companion.toml"))
    defaults = _flat(CompanionConfig())
    assert defaults.keys() == shipped.keys()
    differ = [f"{k}: dataclass default {v!r}, configs/companion.toml {shipped[k]!r}"
              for k, v in defaults.items() if v != shipped[k]]
    assert not differ, "built-in defaults differ from the shipped configuration:\n" + "\n".join(differ)
    assert CompanionConfig() == load_config(None).companion  # no --config: the same configuration


def test_overlay_names_only_what_it_changes(tmp_path):
    base = load_companion_config(ROOT / "configs" / "companion.toml")
    fw = load_companion_config(ROOT / "configs" / "companion_fixedwing.toml")
    changed = {k for k, v in _fields(fw).items() if _fields(base)[k] != v}
    import tomllib

    data = tomllib.loads((ROOT / "configs" / "companion_fixedwing.toml").read_text())
    named = {(t, k) for t, table in data.items() if isinstance(table, dict) for k in table}
    assert data["extends"] == "companion.toml"
    assert changed == named, "the overlay should name exactly the keys it changes"
    assert fw.sectors.max_distance_m == 150.0 and fw.sectors.band_half_height_m == 5.0
    assert fw.harris == base.harris  # everything else comes from the base


def test_overlay_resolution_merge_loops_and_errors(tmp_path):
    (tmp_path / "mine.toml").write_text('extends = "companion.toml"  # shipped (no such file here)\n'
                                        "[sectors]\nmax_distance_m = 25.0  # x\n")
    cfg = load_companion_config(tmp_path / "mine.toml")
    shipped = load_companion_config()
    assert cfg.sectors.max_distance_m == 25.0 and cfg.sectors.band_half_height_m == shipped.sectors.band_half_height_m
    # a base next to the overlay wins over the shipped file of that name, and chains stack
    (tmp_path / "companion.toml").write_text('extends = "companion.toml"  # itself: the shipped one\n'
                                             "[harris]\nk = 0.05  # x\n")
    cfg = load_companion_config(tmp_path / "mine.toml")
    assert cfg.harris.k == 0.05 and cfg.sectors.max_distance_m == 25.0
    (tmp_path / "a.toml").write_text('extends = "b.toml"\n')
    (tmp_path / "b.toml").write_text('extends = "a.toml"\n')
    with pytest.raises(ConfigError, match="levels of extends"):
        load_companion_config(tmp_path / "a.toml")
    (tmp_path / "c.toml").write_text('extends = "nowhere.toml"\n')
    with pytest.raises(ConfigError, match="nowhere.toml"):
        load_companion_config(tmp_path / "c.toml")
    (tmp_path / "d.toml").write_text("extends = 3\n")
    with pytest.raises(ConfigError, match="extends must name"):
        load_companion_config(tmp_path / "d.toml")
    (tmp_path / "e.toml").write_text('extends = "companion.toml"\n[sectors]\nmax_distance = 1.0\n')
    with pytest.raises(ConfigError, match="e.toml.*max_distance"):
        load_companion_config(tmp_path / "e.toml")
