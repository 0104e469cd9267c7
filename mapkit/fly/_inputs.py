"""Incoming ROS 2 messages → checked, typed samples in mapkit's frames (ENU world, FLU body).

Depth and camera info decode with `mapkit ingest`'s own functions (REP 118: 16UC1 millimetres, 32FC1
metres, compressedDepth), so a live stream and a recorded bag read the same. A message that cannot be
used raises :class:`~mapkit.errors.MapkitError` naming what is wrong; the node logs it, rate-limited.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from mapkit.fly._errors import FlyError
from mapkit.fly._frames import R_NED_ENU, R_world_body_from_px4, ned_to_enu
from mapkit.geometry import matrix_from_quat_xyzw
from mapkit.ingest._decode import camera_intrinsics, decode_depth, frame_name, stamp_ns

# px4_msgs/VehicleOdometry frame enums
_PX4_NED, _PX4_FRD, _PX4_BODY_FRD = 1, 2, 3


@dataclass(frozen=True)
class DepthFrame:
    """One depth image, metres (NaN invalid), with its stamp and optical frame."""

    stamp_ns: int
    frame_id: str
    depth: np.ndarray


@dataclass(frozen=True)
class Odometry:
    """The vehicle's pose and velocity, world frame ENU, body FLU."""

    stamp_ns: int
    R_world_body: np.ndarray
    position: np.ndarray
    velocity: np.ndarray

    @property
    def yaw(self) -> float:
        """Heading of the body's x axis, radians counter-clockwise from world +x."""
        return math.atan2(self.R_world_body[1, 0], self.R_world_body[0, 0])

    @property
    def T_world_body(self) -> np.ndarray:
        T = np.eye(4)
        T[:3, :3], T[:3, 3] = self.R_world_body, self.position
        return T


def depth_frame(msg: Any, msgtype: str, topic: str) -> DepthFrame:
    """A depth message decoded (16UC1/mono16 mm, 32FC1 m, compressedDepth)."""
    return DepthFrame(stamp_ns(msg.header), frame_name(msg.header.frame_id), decode_depth(msg, msgtype, topic=topic))


def intrinsics(msg: Any, topic: str) -> tuple[np.ndarray, int, int]:
    """(K, width, height) of a CameraInfo."""
    return camera_intrinsics(msg, topic=topic)


def _finite(values: np.ndarray, what: str) -> np.ndarray:
    if not np.all(np.isfinite(values)):
        raise FlyError(f"odometry {what} {values.tolist()} is not finite; the estimator has no fix")
    return values


def nav_odometry(msg: Any, world_frame: str) -> Odometry:
    """nav_msgs/Odometry: pose in ``header.frame_id`` (must be the world frame), twist in the body frame
    (``child_frame_id``), as REP 105 says."""
    frame = frame_name(msg.header.frame_id)
    if frame != world_frame:
        raise FlyError(f"odometry is in frame {frame!r}, not the world frame {world_frame!r}; "
                       f"pass --set frames.world={frame} or publish odometry in {world_frame!r}")
    p, q, v = msg.pose.pose.position, msg.pose.pose.orientation, msg.twist.twist.linear
    quat = _finite(np.array([q.x, q.y, q.z, q.w]), "orientation")
    if abs(float(np.linalg.norm(quat)) - 1.0) > 1e-2:
        raise FlyError(f"odometry orientation {quat.tolist()} is not a unit quaternion")
    R = matrix_from_quat_xyzw(quat)
    return Odometry(stamp_ns(msg.header), R, _finite(np.array([p.x, p.y, p.z]), "position"),
                    R @ _finite(np.array([v.x, v.y, v.z]), "velocity"))


def px4_odometry(msg: Any, received_ns: int) -> Odometry:
    """px4_msgs/VehicleOdometry (NED or FRD world, FRD body) in ENU/FLU. PX4 stamps are microseconds
    since its boot, so the sample is stamped with its receive time."""
    if int(msg.pose_frame) not in (_PX4_NED, _PX4_FRD):
        raise FlyError(f"PX4 odometry pose_frame {int(msg.pose_frame)} is unknown (1 NED, 2 FRD expected)")
    q = _finite(np.asarray(msg.q, dtype=np.float64), "quaternion")
    R = R_world_body_from_px4(q)
    velocity = _finite(np.asarray(msg.velocity, dtype=np.float64), "velocity")
    if int(msg.velocity_frame) == _PX4_BODY_FRD:
        velocity = R @ np.diag([1.0, -1.0, -1.0]) @ velocity  # FRD body → FLU body → ENU world
    elif int(msg.velocity_frame) in (_PX4_NED, _PX4_FRD):
        velocity = R_NED_ENU.T @ velocity
    else:
        raise FlyError(f"PX4 odometry velocity_frame {int(msg.velocity_frame)} is unknown (1–3 expected)")
    position = ned_to_enu(_finite(np.asarray(msg.position, dtype=np.float64), "position"))
    return Odometry(received_ns, R, position, velocity)


def goal_position(msg: Any, world_frame: str) -> np.ndarray:
    """The position of a geometry_msgs/PoseStamped goal in the world frame."""
    frame = frame_name(msg.header.frame_id)
    if frame not in ("", world_frame):
        raise FlyError(f"goal is in frame {frame!r}; send goals in the world frame {world_frame!r}")
    p = msg.pose.position
    goal = np.array([p.x, p.y, p.z], dtype=np.float64)
    if not np.all(np.isfinite(goal)):
        raise FlyError(f"goal {goal.tolist()} is not finite")
    return goal


def stamp_of(header_ns: int, received_ns: int, max_skew_s: float) -> tuple[int, bool]:
    """The stamp to use for a message: its header's when within `max_skew_s` of the receive time on this
    machine's clock, else the receive time (and False: the clocks disagree)."""
    if abs(header_ns - received_ns) <= max_skew_s * 1e9:
        return header_ns, True
    return received_ns, False
