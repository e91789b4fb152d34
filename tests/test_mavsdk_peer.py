"""MAVSDK 4.x as a ground station reads the DISTANCE_SENSOR the companion produced.

MAVSDK-Python 4.x is the native binding (no gRPC server): ``Mavsdk(Configuration.create_with_
component_type(ComponentType.GROUND_STATION))``, ``add_any_connection("udpin://HOST:PORT")``,
``first_autopilot(timeout)`` and ``Telemetry(system).subscribe_distance_sensor(callback)`` (or the
blocking ``distance_sensor()``), which yields ``current_distance_m``.

Set-up on loopback: the loopback vehicle (a pymavlink peer, component 1) streams telemetry to the
companion and also sends its HEARTBEAT to MAVSDK's port, so MAVSDK discovers an autopilot; the
companion's ground-station output (``--gcs``) sends DISTANCE_SENSOR with the vehicle's system id
and component 196 to the same port, and MAVSDK attributes it to that vehicle.
"""

from __future__ import annotations

import math
import time

import pytest

from companion.mavlink.dialect import mavlink, mavutil  # noqa: I001 (first: MAVLink 2)
from test_pipeline import SYSID, T0, Rig, free_port

mavsdk = pytest.importorskip("mavsdk", reason="mavsdk (MAVSDK-Python 4.x) is not installed")


def _mavsdk_version_ok() -> bool:
    try:
        from importlib.metadata import version

        return int(version("mavsdk").split(".")[0]) >= 4
    except Exception:
        return False


pytestmark = pytest.mark.skipif(not _mavsdk_version_ok(), reason="needs the native MAVSDK-Python binding, mavsdk >= 4")


def test_mavsdk_ground_station_reads_the_companions_distance_sensor():
    from mavsdk import ComponentType, Configuration, Mavsdk
    from mavsdk.plugins.telemetry import Telemetry

    try:
        gs = Mavsdk(Configuration.create_with_component_type(ComponentType.GROUND_STATION))
    except Exception as exc:  # pragma: no cover - a broken native library
        pytest.skip(f"MAVSDK cannot start here: {exc!r}")
    gport = free_port()
    rig = None
    tel = None
    beacon = None
    try:
        assert int(gs.add_any_connection(f"udpin://127.0.0.1:{gport}")) == 0  # ConnectionResult.SUCCESS
        rig = Rig(gcs=f"udpout:127.0.0.1:{gport}")
        # the vehicle's own HEARTBEAT on MAVSDK's port (a vehicle's telemetry radio would carry it)
        beacon = mavutil.mavlink_connection(f"udpout:127.0.0.1:{gport}", source_system=SYSID, source_component=1)

        def beat():
            beacon.mav.heartbeat_send(mavlink.MAV_TYPE_QUADROTOR, mavlink.MAV_AUTOPILOT_PX4, 0, 0, mavlink.MAV_STATE_ACTIVE)

        beat()
        system = gs.first_autopilot(5.0)
        assert system is not None, "MAVSDK did not discover the loopback vehicle"
        tel = Telemetry(system)
        readings = []
        handle = tel.subscribe_distance_sensor(lambda d, _ud: readings.append(d))
        # fly until the companion ranges the wall (simulated clock), keeping the vehicle audible to MAVSDK
        deadline = time.monotonic() + 20.0
        finite = []
        while time.monotonic() < deadline:
            rig.run(0.25)
            beat()
            time.sleep(0.02)
            finite = [d for d in readings if math.isfinite(d.current_distance_m)
                      and d.current_distance_m < d.maximum_distance_m]
            if len(finite) >= 2 and rig.t > T0 + 1.5:
                break
        assert finite, f"MAVSDK got no finite DISTANCE_SENSOR ({len(readings)} readings)"
        truth = rig.flight.wall_distance(rig.t - T0)
        last = finite[-1]
        assert last.current_distance_m == pytest.approx(truth, rel=0.25)
        assert last.minimum_distance_m == pytest.approx(rig.config.sectors.min_distance_m)
        assert last.maximum_distance_m == pytest.approx(rig.config.sectors.max_distance_m)
        # the blocking accessor gives the latest value too
        assert math.isfinite(tel.distance_sensor().current_distance_m)
        tel.unsubscribe_distance_sensor(handle)
    finally:
        if tel is not None:
            tel.destroy()
        if rig is not None:
            rig.close()
        if beacon is not None:
            beacon.close()
        gs.destroy()
