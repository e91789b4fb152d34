"""MAVLink 2 with the ``ardupilotmega`` dialect, whatever was imported before (docs/derivations/link.md).

pymavlink picks MAVLink 1 and the ``all`` dialect unless ``MAVLINK20=1`` is set before import;
OBSTACLE_DISTANCE (330) and OBSTACLE_DISTANCE_3D (11037) do not fit MAVLink 1.  Importing this
module sets the environment and switches ``mavutil`` to MAVLink 2 / ardupilotmega, so every
connection opened afterwards (including tlog readers) speaks MAVLink 2.  Use ``mavlink`` from here
for message classes and enums.
"""

from __future__ import annotations

import os

os.environ["MAVLINK20"] = "1"
os.environ["MAVLINK_DIALECT"] = "ardupilotmega"

from pymavlink import mavutil  # noqa: E402

if mavutil.current_dialect != "ardupilotmega" or mavutil.mavlink.WIRE_PROTOCOL_VERSION != "2.0":
    mavutil.set_dialect("ardupilotmega")

mavlink = mavutil.mavlink

if mavlink.WIRE_PROTOCOL_VERSION != "2.0":  # pragma: no cover - a broken pymavlink install
    raise ImportError("pymavlink could not be switched to MAVLink 2 (ardupilotmega dialect)")

#: Component id of an obstacle-avoidance companion (MAV_COMP_ID_OBSTACLE_AVOIDANCE).
COMP_ID_OBSTACLE_AVOIDANCE = mavlink.MAV_COMP_ID_OBSTACLE_AVOIDANCE
UINT16_MAX = 65535

__all__ = ["mavutil", "mavlink", "COMP_ID_OBSTACLE_AVOIDANCE", "UINT16_MAX"]
