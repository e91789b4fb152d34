"""Flight dynamics for flightsim: JSBSim aircraft shipped in the jsbsim wheel, our autopilots.

* :class:`FixedWingSim` — the J3Cub, trimmed at the start, with heading / altitude / airspeed
  holds and L1 waypoint following;
* :class:`QuadSim` — the F450 (its own body-rate loop) with our attitude, velocity and position
  loops: take-off, hover, straight legs at up to 10 m/s that end at rest, hovers of a set time and
  turns in place by a set angle at a waypoint (``RouteConfig.hold_s`` / ``turn_deg``,
  docs/derivations/sectors.md), hold;
* :class:`VehicleState` — ground truth in the world frame (local NED at the origin, body FRD,
  ZYX roll/pitch/yaw; docs/derivations/frames.md);
* config dataclasses (frozen, validated, fillable by ``companion.config.from_mapping``).

Both vehicles advance in whole JSBSim frames (``sim_rate_hz``, 120 Hz by default) with
``step(dt)`` / ``step(until=t)`` and report ``state()``; the same config (seed included) gives the
same trajectory, bit for bit.
"""

from .config import (
    AIRCRAFT,
    TURBULENCE_TYPES,
    AtmosphereConfig,
    DynamicsConfig,
    FixedWingGains,
    QuadGains,
    RouteConfig,
    check_aircraft,
)
from .fixedwing import FixedWingSim
from .geodesy import LocalNED
from .quad import QuadSim
from .state import VehicleState, stack_states
from .vehicle import JSBSimVehicle, SimulationError


def make_vehicle(config: DynamicsConfig) -> FixedWingSim | QuadSim:
    """The simulator class that flies ``config.aircraft``."""
    return FixedWingSim(config) if config.kind == "fixedwing" else QuadSim(config)


__all__ = [
    "AIRCRAFT",
    "TURBULENCE_TYPES",
    "AtmosphereConfig",
    "DynamicsConfig",
    "FixedWingGains",
    "FixedWingSim",
    "JSBSimVehicle",
    "LocalNED",
    "QuadGains",
    "QuadSim",
    "RouteConfig",
    "SimulationError",
    "VehicleState",
    "check_aircraft",
    "make_vehicle",
    "stack_states",
]
