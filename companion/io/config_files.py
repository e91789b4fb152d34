"""Loading ``configs/*.toml`` into the per-module config dataclasses, and OpenCV calibrations.

The companion TOML has one table per module; each maps onto that module's frozen dataclass via
:func:`companion.config.from_mapping`, so unknown keys, wrong types and out-of-range values stop
with a :class:`ConfigError` that names the file, the table and the key.
"""

from __future__ import annotations

import dataclasses
import os
import re
import sys
from pathlib import Path

import numpy as np

from companion.config import from_mapping
from companion.camera_sources import CameraSourceConfig
from companion.core.camera import CameraConfig
from companion.core.ekf_anchored import AnchoredEKFConfig
from companion.core.ekf_landmark import LandmarkEKFConfig
from companion.core.estimator import EstimatorConfig
from companion.core.harris import HarrisConfig
from companion.core.ncc import NCCConfig
from companion.core.obstacle_map import MapConfig
from companion.core.prediction import PredictionConfig
from companion.core.tracks import TrackConfig
from companion.core.sectors import SectorConfig
from companion.core.triangulation import TriangulationConfig
from companion.mavlink.config import LinkConfig
from companion.mavlink.messages import OutputConfig
from companion.pipeline import PipelineConfig
from companion.telemetry import TelemetryConfig
from companion.errors import ConfigError
from companion.io.inputs import check_input_file, read_input_text

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover - exercised on Python 3.10 only
    import tomli as tomllib


@dataclasses.dataclass(frozen=True)
class CompanionConfig:
    """Every table of ``configs/companion.toml``."""

    camera: CameraConfig = CameraConfig()
    harris: HarrisConfig = HarrisConfig()
    ncc: NCCConfig = NCCConfig()
    prediction: PredictionConfig = PredictionConfig()
    tracks: TrackConfig = TrackConfig()
    triangulation: TriangulationConfig = TriangulationConfig()
    ekf_anchored: AnchoredEKFConfig = AnchoredEKFConfig()
    ekf_landmark: LandmarkEKFConfig = LandmarkEKFConfig()
    estimator: EstimatorConfig = EstimatorConfig()
    sectors: SectorConfig = SectorConfig()
    map: MapConfig = MapConfig()
    telemetry: TelemetryConfig = TelemetryConfig()
    outputs: OutputConfig = OutputConfig()
    link: LinkConfig = LinkConfig()
    camera_source: CameraSourceConfig = CameraSourceConfig()
    pipeline: PipelineConfig = PipelineConfig()


#: the most overlays one configuration may stack (``extends`` chains); a loop stops here with a ConfigError
MAX_EXTENDS_DEPTH = 8


def shipped_config_dir() -> Path:
    """The configuration files shipped with the package (``companion.toml``, its overlays, the
    simulator's scenarios and worlds).  In an installed wheel they are package data
    (``companion/configs/``); in a source checkout (an editable install, the tests) they are the
    repository's ``configs/`` — the same files: the wheel maps that directory into the package."""
    here = Path(__file__).resolve().parents[1]  # the companion package
    for candidate in (here / "configs", here.parent / "configs"):
        if (candidate / "companion.toml").is_file():
            return candidate
    raise ConfigError(f"the shipped configuration is missing (looked in {here / 'configs'} and {here.parent / 'configs'}): "
                      "reinstall the package")


def shipped_config(name: str = "companion.toml") -> Path:
    """Path of one shipped configuration file, e.g. ``companion.toml`` or ``companion_fixedwing.toml``."""
    path = shipped_config_dir() / name
    if not path.is_file():
        raise ConfigError(f"no shipped configuration named {name!r} in {shipped_config_dir()}")
    return path


def _merge(base: dict, overlay: dict) -> dict:
    """``overlay`` on top of ``base``: tables merge key by key, any other value replaces."""
    out = dict(base)
    for key, value in overlay.items():
        out[key] = _merge(out[key], value) if isinstance(value, dict) and isinstance(out.get(key), dict) else value
    return out


def read_config_toml(path: str | os.PathLike, _depth: int = 0) -> dict:
    """A companion TOML with its ``extends`` chain resolved: a file whose top-level ``extends``
    names another (relative to the file, else a shipped configuration of that name) holds only what
    it changes, merged table by table over that base.  ``configs/companion_fixedwing.toml`` is
    ``extends = "companion.toml"`` plus the keys a fixed-wing needs."""
    path = Path(path)
    data = read_toml(path)
    base_name = data.pop("extends", None)
    if base_name is None:
        return data
    if not isinstance(base_name, str) or not base_name:
        raise ConfigError(f"{path}: extends must name a TOML file, got {base_name!r}")
    if _depth >= MAX_EXTENDS_DEPTH:
        raise ConfigError(f"{path}: more than {MAX_EXTENDS_DEPTH} levels of extends (a loop?)")
    base_path = path.parent / base_name
    if not base_path.is_file() or base_path.resolve() == path.resolve():  # a file named like its base extends the shipped one
        base_path = shipped_config(Path(base_name).name)
    return _merge(read_config_toml(base_path, _depth + 1), data)


def read_toml(path: str | os.PathLike, what: str = "configuration") -> dict:
    """Parse a TOML file; a missing, unreadable or non-text file or a syntax error becomes a
    ConfigError naming the file (``what``: the kind of file in the message, e.g. "scenario", "world")."""
    path = Path(path)
    text = read_input_text(path, f"{what} file", allow_empty=True)
    try:
        return tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"{path}: not valid TOML: {exc}") from None


def load_companion_config(path: str | os.PathLike | None = None) -> CompanionConfig:
    """Load and validate the whole companion configuration: ``path`` (overlays resolved, see
    :func:`read_config_toml`), or the shipped ``companion.toml`` when None.  Every command that
    runs the companion loads its configuration here, so "no --config" means exactly the shipped
    file.  The dataclasses' own defaults are that same configuration (``CompanionConfig() ==
    load_companion_config()``, checked key by key by tests/test_config.py), so library use without
    a file behaves like a command."""
    path = shipped_config() if path is None else Path(path)
    data = read_config_toml(path)
    try:
        return from_mapping(CompanionConfig, data, "")
    except ConfigError as exc:
        raise ConfigError(f"{path}: {exc}") from None


def load_opencv_calibration(path: str | os.PathLike, base: CameraConfig | None = None) -> CameraConfig:
    """Camera intrinsics from an OpenCV calibration file (YAML/XML written by ``cv2.FileStorage``).

    Reads ``camera_matrix`` and ``distortion_coefficients`` (and ``image_width`` /
    ``image_height`` when present); the mount and anything missing come from ``base``.  A file
    OpenCV cannot parse, or whose nodes are not what a calibration holds, is a ConfigError naming
    the file, the node and (for a syntax error) the line.
    """
    path = check_input_file(path, "calibration file")
    K, D, width, height = _read_calibration_nodes(path)
    base = base or CameraConfig()
    kw = dict(
        fx=float(K[0, 0]), fy=float(K[1, 1]), cx=float(K[0, 2]), cy=float(K[1, 2]),
        distortion=tuple(float(v) for v in D),
    )
    if width:
        kw["width"] = width
    if height:
        kw["height"] = height
    try:
        return dataclasses.replace(base, **kw)
    except ConfigError as exc:
        raise ConfigError(f"{path}: {exc}") from None


def _read_calibration_nodes(path: Path) -> tuple[np.ndarray, np.ndarray, int | None, int | None]:
    """``(K, D, width or None, height or None)`` of a calibration file, checked for shape and finiteness."""
    import cv2

    try:
        fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ)
    except (cv2.error, SystemError) as exc:  # a parse error surfaces as SystemError wrapping cv2.error
        raise ConfigError(f"{path}: not a calibration file OpenCV can read ({_opencv_reason(exc)})") from None
    try:
        if not fs.isOpened():
            raise ConfigError(f"{path}: OpenCV cannot read this calibration file")
        if not fs.root().isMap():  # a bare value or a sequence: getNode would assert inside OpenCV
            raise ConfigError(f"{path}: not a calibration file (its top level is not a map of named nodes)")
        K = _calibration_matrix(fs, path, "camera_matrix")
        D = _calibration_matrix(fs, path, "distortion_coefficients")
        width, height = (_calibration_int(fs, path, n) for n in ("image_width", "image_height"))
    finally:
        fs.release()
    if np.shape(K) != (3, 3) or not np.all(np.isfinite(K)):
        raise ConfigError(f"{path}: camera_matrix must be a finite 3×3 matrix, got shape {np.shape(K)}")
    D = np.asarray(D, float).reshape(-1)
    if not np.all(np.isfinite(D)):
        raise ConfigError(f"{path}: distortion_coefficients contain NaN or inf")
    return K, D, width, height


def _calibration_matrix(fs, path: Path, name: str) -> np.ndarray:
    """Node ``name`` as an OpenCV matrix (``!!opencv-matrix``); ConfigError if missing or not a matrix."""
    import cv2

    try:
        node = fs.getNode(name)
    except cv2.error as exc:
        raise ConfigError(f"{path}: not a calibration file OpenCV can read ({_opencv_reason(exc)})") from None
    if node.empty() or node.isNone():
        raise ConfigError(f"{path}: {name} missing")
    m = _matrix_node(node) if node.isMap() else None
    if m is None:
        raise ConfigError(f"{path}: {name} is not an OpenCV matrix (!!opencv-matrix with rows, cols, dt, data)")
    return m


def _matrix_node(node) -> np.ndarray | None:
    """An ``!!opencv-matrix`` map (rows, cols, dt, data) read element by element, or None if it is not one.

    Not ``FileNode.mat()``: OpenCV 5.0's reader trusts the node — a matrix without ``cols`` corrupts the
    heap (``free(): invalid next size``, the process aborts later, wherever the allocator notices), so a
    malformed calibration file could take the companion down instead of being a ConfigError.  Every
    field is checked here before any value is read: rows and cols small positive integers, data a
    sequence of exactly rows × cols numbers.
    """
    dims = []
    for key in ("rows", "cols"):
        sub = node.getNode(key)
        if sub.empty() or sub.isNone() or not sub.isInt():
            return None
        v = int(sub.real())
        if not 1 <= v <= 64:
            return None
        dims.append(v)
    dt, data = node.getNode("dt"), node.getNode("data")
    if dt.empty() or not dt.isString() or data.empty() or not data.isSeq() or data.size() != dims[0] * dims[1]:
        return None
    values = []
    for i in range(data.size()):
        item = data.at(i)
        if not (item.isInt() or item.isReal()):
            return None
        values.append(item.real())
    return np.asarray(values, float).reshape(dims)


def _calibration_int(fs, path: Path, name: str) -> int | None:
    """Optional integer node ``name`` (None when absent); ConfigError if it is not a number."""
    import cv2

    try:
        node = fs.getNode(name)
    except cv2.error as exc:
        raise ConfigError(f"{path}: not a calibration file OpenCV can read ({_opencv_reason(exc)})") from None
    if node.empty() or node.isNone():
        return None
    if not (node.isInt() or node.isReal()):
        raise ConfigError(f"{path}: {name} must be a number")
    return int(node.real())


def _opencv_reason(exc: BaseException) -> str:
    """The useful part of an OpenCV error: "line N: what" for a parse error, else its first line."""
    cause = exc.__cause__ or exc.__context__ or exc
    text = str(cause).strip()
    m = re.search(r"in function '.*\((\d+)\): (.*?)'?$", text, flags=re.S)
    if m:
        return f"line {m.group(1)}: {m.group(2).strip()}"
    m = re.search(r"error: \([-\d]+:[^)]*\) (.*)$", text, flags=re.S)
    return (m.group(1) if m else text).splitlines()[0].strip()
