"""What the autopilot does with the companion's ranges: obstacle avoidance in the simulated autopilot.

docs/derivations/sectors.md: an autopilot does not fly on ranges, it limits the pilot's velocity with them, and
the two autopilots differ exactly where a camera is weak — ArduPilot applies no constraint in a
direction without data, PX4 refuses to move into it.  This package models both from their
documented behaviour and source (rules cited per function), so a simulated flight shows whether
the vehicle stops short of an obstacle with the ranges the companion really sent:

* :class:`ArduPilotAvoidance` (:mod:`.ardupilot`) — Copter simple avoidance with a MAVLink proximity sensor
  (``PRX1_TYPE = 2``, ``AVOID_ENABLE`` with the proximity bit; Loiter / Guided velocity):
  ``AP_Proximity_MAV`` → ``AP_Proximity_Boundary_3D`` (8 faces of 45°, per-face minimum,
  ``PRX_FILT`` low-pass, face time-out) → ``AC_Avoid::adjust_velocity_proximity`` (slide or stop,
  back-up, ``AVOID_ACCEL_MAX`` output rate limit);
* :class:`PX4Avoidance` (:mod:`.px4`) — collision prevention in Position mode (``CP_DIST > 0``), the velocity
  form of ``CollisionPrevention::_calculateConstrainedSetpoint`` (PX4 releases up to about v1.14;
  newer releases shape the stick acceleration with the same stopping distance): 36 bins of 10°,
  ``CP_DELAY``, ``CP_GUIDE_ANG``, ``CP_GO_NO_DATA``;
* :class:`NoAvoidance` (:mod:`.base`) — ``model = "none"``: the pilot's demand passes unchanged.

Messages are taken as the autopilot takes them: stamped with their *arrival* time on the
simulation clock (both autopilots ignore ``time_usec``, docs/derivations/sectors.md), in the body frame at the moment
of use (the vehicle's yaw now).  Everything here is pure: the SITL feeds received messages with
:meth:`NoAvoidance.receive` (the base of every model) and the quad's controller asks :meth:`NoAvoidance.limit` every control
tick.  Horizontal only: the vertical demand passes unchanged (the camera's sectors are horizontal).

Scenario TOML, table ``[avoidance]`` (:class:`AvoidanceConfig`, :mod:`.config`); ``flightsim sitl --avoidance
MODEL`` overrides ``model``.

The braking curves and geometry both models use are in :mod:`.common`.  Each module imports only
``config``, ``common`` and ``base``; every name of the package is importable from here, and
:func:`make_avoidance` (below) builds the model a configuration names.
"""

from __future__ import annotations

from flightsim.avoidance.config import BEHAVES, F450_RADIUS_M, MODELS, AvoidanceConfig
from flightsim.avoidance.common import (  # noqa: F401  (the private helpers too: they were importable from here)
    UINT16_MAX,
    _closest_between_segments,
    _closest_on_segment,
    _increment_deg,
    _isclose,
    _wrap360,
    body_to_ned,
    jerk_limited_speed,
    ned_to_body,
    sqrt_controller,
    stopping_distance,
)
from flightsim.avoidance.base import NoAvoidance
from flightsim.avoidance.ardupilot import ArduPilotAvoidance
from flightsim.avoidance.px4 import PX4Avoidance


def make_avoidance(config: AvoidanceConfig) -> NoAvoidance:
    """The model ``config.model`` names."""
    return {"none": NoAvoidance, "ardupilot": ArduPilotAvoidance, "px4": PX4Avoidance}[config.model](config)


__all__ = ["AvoidanceConfig", "ArduPilotAvoidance", "PX4Avoidance", "NoAvoidance", "make_avoidance", "MODELS",
           "F450_RADIUS_M", "sqrt_controller", "stopping_distance", "jerk_limited_speed"]
