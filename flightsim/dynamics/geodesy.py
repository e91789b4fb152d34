"""WGS-84 geodetic <-> local NED about a fixed origin (docs/derivations/frames.md, world frame).

The world frame of the simulator is the local tangent plane (north, east, down) at a geodetic
origin: ``p_ned`` is the exact ECEF displacement from the origin rotated into that plane, so it is
Euclidean (straight lines stay straight, which the renderer relies on).  Over a few kilometres the
plane departs from the ellipsoid by d²/(2R) (8 cm at 1 km), and the local vertical at the vehicle
tilts by d/R (0.01° at 1 km) from the origin's; both are far below anything the companion resolves.

Scalar functions work on Python floats (they run inside the control loop, where numpy call
overhead would dominate); :func:`R_ecef_ned` returns a numpy matrix for the rarer frame rotations.
"""

from __future__ import annotations

import math

import numpy as np

WGS84_A = 6378137.0  #: semi-major axis, m
WGS84_F = 1.0 / 298.257223563  #: flattening
WGS84_E2 = WGS84_F * (2.0 - WGS84_F)  #: first eccentricity squared
WGS84_B = WGS84_A * (1.0 - WGS84_F)  #: semi-minor axis, m
_EP2 = WGS84_E2 / (1.0 - WGS84_E2)  #: second eccentricity squared


def geodetic_to_ecef(lat_rad: float, lon_rad: float, alt_m: float) -> tuple[float, float, float]:
    """ECEF position (m) of a geodetic point (latitude, longitude in rad, height above the ellipsoid)."""
    sl, cl = math.sin(lat_rad), math.cos(lat_rad)
    n = WGS84_A / math.sqrt(1.0 - WGS84_E2 * sl * sl)
    return ((n + alt_m) * cl * math.cos(lon_rad), (n + alt_m) * cl * math.sin(lon_rad), (n * (1.0 - WGS84_E2) + alt_m) * sl)


def ecef_to_geodetic(x: float, y: float, z: float) -> tuple[float, float, float]:
    """Inverse of :func:`geodetic_to_ecef`: (lat rad, lon rad, alt m).

    Bowring's parametric-latitude start followed by two Newton-like refinements; sub-millimetre
    for any point near the Earth's surface.
    """
    lon = math.atan2(y, x)
    p = math.hypot(x, y)
    beta = math.atan2(z * WGS84_A, p * WGS84_B)
    lat = 0.0
    for _ in range(3):
        sb, cb = math.sin(beta), math.cos(beta)
        lat = math.atan2(z + _EP2 * WGS84_B * sb**3, p - WGS84_E2 * WGS84_A * cb**3)
        beta = math.atan2((1.0 - WGS84_F) * math.sin(lat), math.cos(lat))
    sl, cl = math.sin(lat), math.cos(lat)
    n = WGS84_A / math.sqrt(1.0 - WGS84_E2 * sl * sl)
    if abs(cl) > 1e-9:
        alt = p / cl - n
    else:  # at a pole
        alt = abs(z) - WGS84_B
    return lat, lon, alt


def R_ecef_ned(lat_rad: float, lon_rad: float) -> np.ndarray:
    """``R_ecef_ned``: maps NED vectors at (lat, lon) into ECEF (columns = north, east, down)."""
    sl, cl = math.sin(lat_rad), math.cos(lat_rad)
    so, co = math.sin(lon_rad), math.cos(lon_rad)
    return np.array(
        [
            [-sl * co, -so, -cl * co],
            [-sl * so, co, -cl * so],
            [cl, 0.0, -sl],
        ]
    )


class LocalNED:
    """Local tangent-plane NED frame at a geodetic origin (lat, lon in degrees, alt in m)."""

    def __init__(self, lat_deg: float, lon_deg: float, alt_m: float) -> None:
        self.lat_deg = float(lat_deg)
        self.lon_deg = float(lon_deg)
        self.alt_m = float(alt_m)
        lat, lon = math.radians(lat_deg), math.radians(lon_deg)
        self._o = geodetic_to_ecef(lat, lon, alt_m)
        R = R_ecef_ned(lat, lon)
        self.R_ecef_ned = R
        self.R_ned_ecef = R.T.copy()
        self._rows = tuple(tuple(float(v) for v in row) for row in self.R_ned_ecef)

    def from_geodetic(self, lat_rad: float, lon_rad: float, alt_m: float) -> tuple[float, float, float]:
        """NED position (m) of a geodetic point, relative to the origin."""
        x, y, z = geodetic_to_ecef(lat_rad, lon_rad, alt_m)
        dx, dy, dz = x - self._o[0], y - self._o[1], z - self._o[2]
        (a, b, c), (d, e, f), (g, h, i) = self._rows
        return (a * dx + b * dy + c * dz, d * dx + e * dy + f * dz, g * dx + h * dy + i * dz)

    def to_geodetic(self, n: float, e: float, d: float) -> tuple[float, float, float]:
        """Geodetic (lat rad, lon rad, alt m) of a NED position relative to the origin."""
        R = self.R_ecef_ned
        x = self._o[0] + R[0, 0] * n + R[0, 1] * e + R[0, 2] * d
        y = self._o[1] + R[1, 0] * n + R[1, 1] * e + R[1, 2] * d
        z = self._o[2] + R[2, 0] * n + R[2, 1] * e + R[2, 2] * d
        return ecef_to_geodetic(float(x), float(y), float(z))

    def R_world_localned(self, lat_rad: float, lon_rad: float) -> np.ndarray:
        """Rotation from the local-level NED frame at (lat, lon) into the origin's NED (world) frame."""
        return self.R_ned_ecef @ R_ecef_ned(lat_rad, lon_rad)
