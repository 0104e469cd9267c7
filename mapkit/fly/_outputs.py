"""What `mapkit fly` publishes, as rosbags message objects: PX4's TrajectorySetpoint (NED) and
OffboardControlMode, a MultiDOFJointTrajectory setpoint for other autopilots, the plan as a Path, and
the status as JSON text."""

from __future__ import annotations

import json
import math
from typing import Any

import numpy as np

from mapkit.flight import Reference, Setpoint
from mapkit.fly._frames import enu_to_ned, yaw_enu_to_ned
from mapkit.fly._msgs import message

PATH_STEP = 0.1
"""Seconds between the published path's poses."""


def _time(stamp_ns: int) -> Any:
    return message("builtin_interfaces/msg/Time", sec=int(stamp_ns // 1_000_000_000), nanosec=int(stamp_ns % 1_000_000_000))


def header(stamp_ns: int, frame_id: str) -> Any:
    return message("std_msgs/msg/Header", stamp=_time(stamp_ns), frame_id=frame_id)


def _vector3(v: np.ndarray) -> Any:
    return message("geometry_msgs/msg/Vector3", x=float(v[0]), y=float(v[1]), z=float(v[2]))


def _yaw_quaternion(yaw: float) -> Any:
    return message("geometry_msgs/msg/Quaternion", x=0.0, y=0.0, z=math.sin(yaw / 2), w=math.cos(yaw / 2))


def px4_setpoint(sp: Setpoint, stamp_ns: int) -> Any:
    """px4_msgs/TrajectorySetpoint of a setpoint: NED, yaw clockwise from north (timestamp µs)."""
    f32 = np.float32
    return message(
        "px4_msgs/msg/TrajectorySetpoint", timestamp=stamp_ns // 1000,
        position=enu_to_ned(sp.position).astype(f32), velocity=enu_to_ned(sp.velocity).astype(f32),
        acceleration=enu_to_ned(sp.acceleration).astype(f32), jerk=enu_to_ned(sp.jerk).astype(f32),
        yaw=yaw_enu_to_ned(sp.yaw), yawspeed=-sp.yaw_rate,
    )


def px4_offboard(stamp_ns: int) -> Any:
    """px4_msgs/OffboardControlMode: position, velocity and acceleration are controlled."""
    return message("px4_msgs/msg/OffboardControlMode", timestamp=stamp_ns // 1000, position=True, velocity=True,
                   acceleration=True, attitude=False, body_rate=False, thrust_and_torque=False, direct_actuator=False)


def multidof_setpoint(sp: Setpoint, stamp_ns: int, world_frame: str, body_frame: str) -> Any:
    """trajectory_msgs/MultiDOFJointTrajectory with one point: pose (yaw), velocity (yaw rate) and acceleration."""
    zero = np.zeros(3)
    point = message(
        "trajectory_msgs/msg/MultiDOFJointTrajectoryPoint",
        transforms=[message("geometry_msgs/msg/Transform", translation=_vector3(sp.position),
                            rotation=_yaw_quaternion(sp.yaw))],
        velocities=[message("geometry_msgs/msg/Twist", linear=_vector3(sp.velocity),
                            angular=_vector3(np.array([0.0, 0.0, sp.yaw_rate])))],
        accelerations=[message("geometry_msgs/msg/Twist", linear=_vector3(sp.acceleration), angular=_vector3(zero))],
        time_from_start=message("builtin_interfaces/msg/Duration", sec=0, nanosec=0),
    )
    return message("trajectory_msgs/msg/MultiDOFJointTrajectory", header=header(stamp_ns, world_frame),
                   joint_names=[body_frame], points=[point])


def path(reference: Reference, t_now: float, stamp_ns: int, world_frame: str) -> Any:
    """nav_msgs/Path of the reference from `t_now` to its end (poses every :data:`PATH_STEP` s)."""
    end = max(t_now, reference.t_end)
    times = np.linspace(t_now, end, max(2, int(math.ceil((end - t_now) / PATH_STEP)) + 1))
    positions, yaws = reference.derivative(times, 0), reference.yaw(times)
    poses = []
    for t, p, yaw in zip(times, positions, yaws, strict=True):
        pose = message("geometry_msgs/msg/Pose", position=message("geometry_msgs/msg/Point", x=float(p[0]),
                       y=float(p[1]), z=float(p[2])), orientation=_yaw_quaternion(float(yaw)))
        poses.append(message("geometry_msgs/msg/PoseStamped", header=header(stamp_ns + int((t - t_now) * 1e9),
                             world_frame), pose=pose))
    return message("nav_msgs/msg/Path", header=header(stamp_ns, world_frame), poses=poses)


def status(fields: dict[str, Any]) -> Any:
    """std_msgs/String holding one JSON object."""
    return message("std_msgs/msg/String", data=json.dumps(fields, sort_keys=True))
