"""Ground-truth vehicle state in the project's frames (docs/derivations/frames.md)."""

from __future__ import annotations

import functools
from dataclasses import dataclass, fields

import numpy as np

from companion.core.frames import euler_zyx_to_R


@dataclass(frozen=True, eq=False)
class VehicleState:
    """True state of the simulated vehicle at ``time_s``.

    * ``p_ned``: centre of gravity in the world frame (local NED at the origin), m;
    * ``v_ned``: its velocity over ground in the world frame, m/s;
    * ``rpy``: roll, pitch, yaw (ZYX, rad) of body FRD relative to the world frame — what
      MAVLink ATTITUDE reports; yaw in (−π, π];
    * ``pqr``: body angular rates (FRD, rad/s) relative to the Earth;
    * ``lat_deg``, ``lon_deg``: geodetic WGS-84, ``alt_m``: height above the ellipsoid;
    * ``airspeed_mps``: true airspeed; ``on_ground``: any landing gear touches the ground.
    """

    time_s: float
    p_ned: np.ndarray
    v_ned: np.ndarray
    rpy: np.ndarray
    pqr: np.ndarray
    lat_deg: float
    lon_deg: float
    alt_m: float
    airspeed_mps: float
    on_ground: bool = False

    def __post_init__(self) -> None:
        for name in ("p_ned", "v_ned", "rpy", "pqr"):
            a = np.array(getattr(self, name), dtype=float)  # own copy, read-only: truth is immutable
            if a.shape != (3,):
                raise ValueError(f"VehicleState.{name} must have shape (3,), got {a.shape}")
            a.flags.writeable = False
            object.__setattr__(self, name, a)

    @functools.cached_property
    def R_world_body(self) -> np.ndarray:
        """Rotation body FRD → world NED (computed from ``rpy`` once per state, read-only: the
        simulator asks for it several times a step — telemetry, camera pose, truth)."""
        R = euler_zyx_to_R(*self.rpy)
        R.flags.writeable = False
        return R

    @property
    def altitude_m(self) -> float:
        """Height above the world origin (−p_ned[2])."""
        return float(-self.p_ned[2])

    @property
    def ground_speed_mps(self) -> float:
        return float(np.hypot(self.v_ned[0], self.v_ned[1]))

    @property
    def course_rad(self) -> float:
        """Direction of the horizontal ground velocity (rad from north, clockwise)."""
        return float(np.arctan2(self.v_ned[1], self.v_ned[0]))

    def __eq__(self, other: object) -> bool:
        if not isinstance(other, VehicleState):
            return NotImplemented
        return all(np.array_equal(getattr(self, f.name), getattr(other, f.name)) for f in fields(self))

    __hash__ = None  # type: ignore[assignment]


def stack_states(states: list[VehicleState]) -> dict[str, np.ndarray]:
    """Column arrays of a list of states: ``{"time_s": (N,), "p_ned": (N, 3), …}``."""
    return {f.name: np.array([getattr(s, f.name) for s in states]) for f in fields(VehicleState)}
