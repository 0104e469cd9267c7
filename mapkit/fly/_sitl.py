"""Software in the loop over DDS: a simulated vehicle that a `mapkit fly` node flies through real topics.

:class:`SimulatedVehicle` is the robot side of the link: a `mapkit.sim` world, its depth camera and
rotorpy's quadrotor under its SE(3) controller (as `mapkit eval --vehicle rotorpy`), run in real time.
It publishes depth (16UC1, the common driver encoding), camera info, odometry and the camera mount on
/tf_static, sends the goal, and flies the setpoints it receives on PX4's topic (NED, converted back),
holding the last one between them, as PX4's offboard mode does. A flight is judged as `mapkit eval`
judges it: the body centre closer than the robot radius to the world is a collision, within the goal
radius a success, past the time limit a timeout.
"""

from __future__ import annotations

import math
import threading
import time
from dataclasses import dataclass
from typing import Any, Literal

import numpy as np

from mapkit.evaluation._rotorpy import RATE_HZ
from mapkit.flight import RunCamera, Setpoint
from mapkit.fly._config import ODOMETRY_TYPES, FlyConfig
from mapkit.fly._dds import Link
from mapkit.fly._frames import enu_to_ned, ned_to_enu, px4_quaternion, yaw_ned_to_enu
from mapkit.fly._msgs import message
from mapkit.fly._outputs import header
from mapkit.geometry import quat_xyzw_from_matrix

Outcome = Literal["success", "collision", "timeout", "no link"]


@dataclass
class SitlFlight:
    """One flight of the simulated vehicle."""

    outcome: Outcome
    time_s: float
    """Seconds from the goal to the end."""
    min_distance: float
    """Smallest distance from the body centre to the world, metres."""
    setpoints: int
    """Setpoints received."""
    path: np.ndarray
    """(N, 4) rows [t, x, y, z] at the simulation rate."""


def setpoint_from_px4(msg: Any, t: float) -> Setpoint:
    """A PX4 TrajectorySetpoint (NED) as a mapkit setpoint (ENU); NaN fields count as zero."""
    def vec(v: Any) -> np.ndarray:
        return ned_to_enu(np.nan_to_num(np.asarray(v, dtype=np.float64)))

    return Setpoint(t=t, position=vec(msg.position), velocity=vec(msg.velocity), acceleration=vec(msg.acceleration),
                    jerk=vec(msg.jerk), snap=np.zeros(3), yaw=yaw_ned_to_enu(float(msg.yaw)),
                    yaw_rate=-float(msg.yawspeed))


class _Judge:
    """`mapkit eval`'s verdict on a flight, sample by sample: the first sample closer than the robot
    radius to the world is a collision, within the goal radius a success."""

    def __init__(self, world: Any, goal: np.ndarray, goal_radius: float, robot_radius: float,
                 rows: list[np.ndarray], t0: float) -> None:
        self.world, self.goal, self.goal_radius, self.robot_radius, self.rows = world, goal, goal_radius, robot_radius, rows
        self.t0 = t0
        self.outcome: Outcome = "timeout"
        self.min_distance = math.inf

    def done(self, t: float, position: np.ndarray) -> bool:
        d = float(self.world.signed_distance(position[None])[0])
        self.min_distance = min(self.min_distance, d)
        self.rows.append(np.array([t, *position]))
        if d < self.robot_radius:
            self.outcome = "collision"
        elif float(np.linalg.norm(position - self.goal)) <= self.goal_radius:
            self.outcome = "success"
        return self.outcome != "timeout"


class SimulatedVehicle:
    """The robot side of a software-in-the-loop flight (see the module docstring)."""

    def __init__(self, link: Link, world: Any, camera: RunCamera, config: FlyConfig, *,
                 depth_rate: float = 30.0, odometry_rate: float = 100.0) -> None:
        """`config` names the topics the node uses; its ``topics.odometry_type`` says which odometry to
        publish (nav_msgs/Odometry in ENU/FLU, or PX4's VehicleOdometry in NED/FRD)."""
        from mapkit.evaluation._rotorpy import RotorpyVehicle
        from mapkit.sim import CameraModel

        self.link, self.world, self.camera, self.config = link, world, camera, config
        self.depth_rate, self.odometry_rate = depth_rate, odometry_rate
        K = camera.K
        self._model = CameraModel(width=camera.width, height=camera.height, fx=float(K[0, 0]), fy=float(K[1, 1]))
        self._vehicle = RotorpyVehicle()
        self._lock = threading.Lock()
        self._setpoint: Setpoint | None = None
        self._received = 0
        self._t = 1.0  # simulator seconds: never reset (the node's clock must not go back)
        self._next_depth = self._next_odometry = self._t
        self.fault_after: float | None = None
        """Seconds into a flight after which the `fault` input stops publishing (the other goes on)."""
        self.fault: Literal["depth", "odometry"] = "depth"
        t = config.topics
        self._pub_depth = link.writer(t.depth, "sensor_msgs/msg/Image", qos="sensor")
        self._pub_info = link.writer(t.camera_info, "sensor_msgs/msg/CameraInfo", qos="sensor")
        self._pub_odometry = link.writer(t.odometry_topic, ODOMETRY_TYPES[t.odometry_type], qos="sensor")
        self._pub_tf_static = link.writer(t.tf_static, "tf2_msgs/msg/TFMessage", qos="latched")
        self._pub_goal = link.writer(t.goal, "geometry_msgs/msg/PoseStamped", qos="reliable")
        self._pub_clock = link.writer(t.clock, "rosgraph_msgs/msg/Clock", qos="reliable")
        link.reader(t.px4_setpoint, "px4_msgs/msg/TrajectorySetpoint", self._on_setpoint, qos="reliable")

    def _on_setpoint(self, msg: Any, received_ns: int) -> None:
        sp = setpoint_from_px4(msg, self._t)
        with self._lock:
            self._setpoint = sp
            self._received += 1

    def _flat(self, start: np.ndarray, yaw: float, *, offboard: bool) -> Any:
        """rotorpy's reference: offboard, the last setpoint received, held; else a hover at `start`."""
        rest = Setpoint(0.0, start, np.zeros(3), np.zeros(3), np.zeros(3), np.zeros(3), yaw, 0.0)

        def flat(t: float) -> Setpoint:
            if not offboard:
                return rest
            with self._lock:
                return self._setpoint or rest

        return flat

    def wait_for_node(self, timeout: float = 20.0) -> bool:
        """True once a node reads odometry and depth and writes setpoints (discovery done)."""
        t = self.config.topics
        end = time.monotonic() + timeout
        while time.monotonic() < end:
            if min(self.link.matched(t.odometry_topic), self.link.matched(t.depth), self.link.matched(t.px4_setpoint),
                   self.link.matched(t.goal)) > 0:
                return True
            time.sleep(0.05)
        return False

    def fly(self, start: np.ndarray, goal: np.ndarray, *, time_limit: float, goal_radius: float = 0.5,
            robot_radius: float = 0.3, settle: float = 1.0) -> SitlFlight:
        """Place the vehicle at `start` facing `goal` and let it hover there on its own for `settle` seconds
        (PX4's hold mode; the node sees odometry jump there, drops its goal and streams a hold), then send the goal and
        fly the node's setpoints (offboard) until success, collision or `time_limit` seconds."""
        start, goal = np.asarray(start, dtype=np.float64), np.asarray(goal, dtype=np.float64)
        yaw = math.atan2(goal[1] - start[1], goal[0] - start[0])
        self._vehicle.reset(start, yaw)
        self._publish_mount()
        self._run(self._t + settle, None, self._flat(start, yaw, offboard=False))
        with self._lock:
            self._received = 0
        self._publish_goal(goal)
        t_goal = self._t
        rows: list[np.ndarray] = []
        judge = _Judge(self.world, goal, goal_radius, robot_radius, rows, t_goal)
        outcome, d_min = self._run(t_goal + time_limit, judge, self._flat(start, yaw, offboard=True))
        with self._lock:
            received = self._received
        return SitlFlight(outcome, self._t - t_goal, d_min, received, np.array(rows).reshape(-1, 4))

    def hover(self, position: np.ndarray, seconds: float) -> None:
        """Place the vehicle at `position` and let it hover on its own for `seconds` (no goal is sent)."""
        position = np.asarray(position, dtype=np.float64)
        self._vehicle.reset(position, 0.0)
        self._publish_mount()
        self._run(self._t + seconds, None, self._flat(position, 0.0, offboard=False))

    def _run(self, t_end: float, judge: _Judge | None, flat: Any) -> tuple[Outcome, float]:
        """Fly `flat` until `t_end` (simulator seconds; no faster than real time), publishing /clock and the
        sensors at their rates, and `judge` the flight (None: not judged, the vehicle is being placed)."""
        dt = 1.0 / RATE_HZ
        wall0, t0 = time.monotonic(), self._t
        while self._t < t_end - 1e-9:
            self._publish_clock()
            lost = None if judge is None or self.fault_after is None or self._t - judge.t0 < self.fault_after \
                else self.fault
            if self._t >= self._next_odometry:
                if lost != "odometry":
                    self._publish_odometry()
                self._next_odometry += 1.0 / self.odometry_rate
            if self._t >= self._next_depth:
                if lost != "depth":
                    self._publish_depth()
                self._next_depth += 1.0 / self.depth_rate
            self._vehicle.fly(flat, self._t, self._t + dt)
            self._t += dt
            if judge is not None and judge.done(self._t, self._vehicle.position):
                break
            ahead = (self._t - t0) - (time.monotonic() - wall0)
            if ahead > 0:
                time.sleep(ahead)
        return ("timeout", math.inf) if judge is None else (judge.outcome, judge.min_distance)

    def _ns(self) -> int:
        return int(round(self._t * 1e9))

    def _publish_clock(self) -> None:
        self._pub_clock(message("rosgraph_msgs/msg/Clock", clock=header(self._ns(), "").stamp))

    def _publish_odometry(self) -> None:
        T, velocity = self._vehicle.T_world_body, self._vehicle.velocity
        if self.config.topics.odometry_type == "px4":
            f32 = np.float32
            nan3 = np.full(3, np.nan, f32)
            self._pub_odometry(message(
                "px4_msgs/msg/VehicleOdometry", timestamp=self._ns() // 1000, timestamp_sample=self._ns() // 1000,
                pose_frame=1, position=enu_to_ned(T[:3, 3]).astype(f32), q=px4_quaternion(T[:3, :3]).astype(f32),
                velocity_frame=1, velocity=enu_to_ned(velocity).astype(f32), angular_velocity=nan3,
                position_variance=nan3, orientation_variance=nan3, velocity_variance=nan3, reset_counter=0, quality=0))
            return
        c = self.config.frames
        q = quat_xyzw_from_matrix(T[:3, :3])
        v_body = T[:3, :3].T @ velocity  # nav_msgs/Odometry's twist is in the body frame
        pose = message("geometry_msgs/msg/PoseWithCovariance", pose=message(
            "geometry_msgs/msg/Pose", position=message("geometry_msgs/msg/Point", x=T[0, 3], y=T[1, 3], z=T[2, 3]),
            orientation=message("geometry_msgs/msg/Quaternion", x=q[0], y=q[1], z=q[2], w=q[3])),
            covariance=np.zeros(36))
        twist = message("geometry_msgs/msg/TwistWithCovariance", twist=message(
            "geometry_msgs/msg/Twist", linear=message("geometry_msgs/msg/Vector3", x=v_body[0], y=v_body[1], z=v_body[2]),
            angular=message("geometry_msgs/msg/Vector3", x=0.0, y=0.0, z=0.0)), covariance=np.zeros(36))
        self._pub_odometry(message("nav_msgs/msg/Odometry", header=header(self._ns(), c.world),
                                   child_frame_id=c.body, pose=pose, twist=twist))

    def _publish_depth(self) -> None:
        from mapkit.sim import render_depth

        depth = render_depth(self.world, self._vehicle.T_world_body @ self.camera.T_body_camera, self._model)
        mm = np.where(np.isfinite(depth), np.round(depth * 1000.0), 0).astype("<u2")
        cam = self.camera
        self._pub_info(message(
            "sensor_msgs/msg/CameraInfo", header=header(self._ns(), "camera_optical"), height=cam.height,
            width=cam.width, distortion_model="plumb_bob", d=np.zeros(5), k=cam.K.ravel(), r=np.eye(3).ravel(),
            p=np.hstack([cam.K, np.zeros((3, 1))]).ravel(), binning_x=0, binning_y=0,
            roi=message("sensor_msgs/msg/RegionOfInterest", x_offset=0, y_offset=0, height=0, width=0, do_rectify=False)))
        self._pub_depth(message("sensor_msgs/msg/Image", header=header(self._ns(), "camera_optical"),
                                height=cam.height, width=cam.width, encoding="16UC1", is_bigendian=0,
                                step=2 * cam.width, data=mm.view(np.uint8).ravel()))

    def _publish_mount(self) -> None:
        T = self.camera.T_body_camera
        q = quat_xyzw_from_matrix(T[:3, :3])
        transform = message("geometry_msgs/msg/TransformStamped", header=header(self._ns(), self.config.frames.body),
                            child_frame_id="camera_optical", transform=message(
                                "geometry_msgs/msg/Transform",
                                translation=message("geometry_msgs/msg/Vector3", x=T[0, 3], y=T[1, 3], z=T[2, 3]),
                                rotation=message("geometry_msgs/msg/Quaternion", x=q[0], y=q[1], z=q[2], w=q[3])))
        self._pub_tf_static(message("tf2_msgs/msg/TFMessage", transforms=[transform]))

    def _publish_goal(self, goal: np.ndarray) -> None:
        pose = message("geometry_msgs/msg/Pose", position=message("geometry_msgs/msg/Point", x=goal[0], y=goal[1],
                                                                  z=goal[2]),
                       orientation=message("geometry_msgs/msg/Quaternion", x=0.0, y=0.0, z=0.0, w=1.0))
        self._pub_goal(message("geometry_msgs/msg/PoseStamped", header=header(self._ns(), self.config.frames.world),
                               pose=pose))
