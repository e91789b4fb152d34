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
from companion.mavlink.link import LinkConfig
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


def read_toml(path: str | os.PathLike, what: str = "configuration") -> dict:
    """Parse a TOML file; a missing, unreadable or non-text file or a syntax error becomes a
    ConfigError naming the file (``what``: the kind of file in the message, e.g. "scenario", "world")."""
    path = Path(path)
    text = read_input_text(path, f"{what} file", allow_empty=True)
    try:
        return tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"{path}: not valid TOML: {exc}") from None


def load_companion_config(path: str | os.PathLike) -> CompanionConfig:
    """Load and validate the whole companion configuration."""
    data = read_toml(path)
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

    node = fs.getNode(name)
    if node.empty() or node.isNone():
        raise ConfigError(f"{path}: {name} missing")
    try:
        m = node.mat() if node.isMap() else None
    except cv2.error:
        m = None
    if m is None:
        raise ConfigError(f"{path}: {name} is not an OpenCV matrix (!!opencv-matrix with rows, cols, dt, data)")
    return np.asarray(m, float)


def _calibration_int(fs, path: Path, name: str) -> int | None:
    """Optional integer node ``name`` (None when absent); ConfigError if it is not a number."""
    node = fs.getNode(name)
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
