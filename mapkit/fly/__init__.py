"""Flying the pilot on a real vehicle: `mapkit fly`, a live ROS 2 / PX4 link over DDS without a ROS
installation (Eclipse Cyclone DDS; message types from the same definitions mapkit's bag readers use).

>>> from mapkit.fly import FlyConfig, fly
>>> summary = fly("pretrained", FlyConfig())   # until Ctrl-C        # doctest: +SKIP

``docs/fly.md`` says how to wire it to PX4 (uXRCE-DDS, offboard) or a ROS 2 robot, and what it does
when inputs stop or misbehave. :class:`SimulatedVehicle` is the other end for software in the loop.
"""

from mapkit.fly._config import DEPTH_TYPES, ODOMETRY_TYPES, FlyConfig, Frames, Topics
from mapkit.fly._dds import LOOPBACK, DdsConfig, Link, dds_topic
from mapkit.fly._errors import FlyError
from mapkit.fly._frames import (
    R_world_body_from_px4,
    enu_to_ned,
    ned_to_enu,
    px4_quaternion,
    yaw_enu_to_ned,
    yaw_ned_to_enu,
)
from mapkit.fly._msgs import dds_type, dds_typename, decode, encode, message, typestore
from mapkit.fly._node import FlyNode, TimedStep
from mapkit.fly._record import Recording
from mapkit.fly._run import FlySummary, fly
from mapkit.fly._sitl import SimulatedVehicle, SitlFlight, setpoint_from_px4

__all__ = [
    "DEPTH_TYPES", "LOOPBACK", "ODOMETRY_TYPES",
    "DdsConfig", "FlyConfig", "FlyError", "FlyNode", "FlySummary", "Frames", "Link", "Recording", "SimulatedVehicle",
    "SitlFlight", "TimedStep", "Topics",
    "R_world_body_from_px4", "dds_topic", "dds_type", "dds_typename", "decode", "encode", "enu_to_ned", "fly",
    "message", "ned_to_enu", "px4_quaternion", "setpoint_from_px4", "typestore", "yaw_enu_to_ned", "yaw_ned_to_enu",
]
