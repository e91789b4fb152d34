"""How many times faster than real time the vehicles fly (batch mode, one core).

``python -m flightsim.dynamics.bench [seconds]`` flies each case for the given simulated time,
reading the state at 30 Hz as a renderer would, and prints simulated / wall-clock time.
"""

from __future__ import annotations

import sys
import time

from .config import AtmosphereConfig, DynamicsConfig, RouteConfig
from .fixedwing import FixedWingSim
from .quad import QuadSim


def realtime_factor(sim, duration_s: float, sample_hz: float = 30.0) -> float:
    """Simulated seconds per wall-clock second over ``duration_s`` of flight, sampling the state."""
    t0 = time.perf_counter()
    sim.run(duration_s, 1.0 / sample_hz)
    return duration_s / (time.perf_counter() - t0)


def cases() -> dict[str, object]:
    turb = AtmosphereConfig(wind_ned_mps=(3.0, -4.0, 0.0), turbulence="milspec", turbulence_wind_20ft_mps=8.0)
    wps = ((1500.0, 0.0, -150.0), (1500.0, 1500.0, -170.0), (0.0, 1500.0, -150.0), (0.0, 0.0, -150.0))

    def quad_line() -> QuadSim:
        q = QuadSim(DynamicsConfig(aircraft="F450", start_ned_m=(0.0, 0.0, 0.0)))
        q.takeoff(10.0)
        for i in range(1, 20):
            q.goto((40.0 * (i % 2), 30.0 * (i % 2), -10.0), speed_mps=10.0)
        return q

    return {
        "J3Cub hold, calm": lambda: FixedWingSim(DynamicsConfig(aircraft="J3Cub", start_ned_m=(0.0, 0.0, -150.0))),
        "J3Cub route, wind+turbulence": lambda: FixedWingSim(
            DynamicsConfig(aircraft="J3Cub", start_ned_m=(0.0, 0.0, -150.0), atmosphere=turb, route=RouteConfig(waypoints=wps, loop=True))
        ),
        "F450 hover, calm": lambda: QuadSim(DynamicsConfig(aircraft="F450", start_ned_m=(0.0, 0.0, -10.0))),
        "F450 take-off + lines at 10 m/s": quad_line,
        "F450 hover, wind+turbulence": lambda: QuadSim(DynamicsConfig(aircraft="F450", start_ned_m=(0.0, 0.0, -10.0), atmosphere=turb)),
    }


def main(argv: list[str] | None = None) -> None:
    argv = sys.argv[1:] if argv is None else argv
    duration = float(argv[0]) if argv else 120.0
    for name, make in cases().items():
        sim = make()
        print(f"{name:34s} {realtime_factor(sim, duration):8.0f} x real time")


if __name__ == "__main__":
    main()
