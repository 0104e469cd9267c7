"""`mapkit fly`'s typed options: topics, QoS and frames (ROS's usual defaults), the setpoint stream,
timeouts and the geofence."""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

from mapkit.flight import PilotConfig
from mapkit.fly._dds import QOS_NAMES, DdsConfig, dds_topic
from mapkit.fly._errors import FlyError

DEPTH_TYPES = {"image": "sensor_msgs/msg/Image", "compressed": "sensor_msgs/msg/CompressedImage"}
ODOMETRY_TYPES = {"nav_msgs": "nav_msgs/msg/Odometry", "px4": "px4_msgs/msg/VehicleOdometry"}


@dataclass(frozen=True)
class Topics:
    """ROS 2 topic names, QoS and message kinds."""

    depth: str = "/camera/depth/image_rect_raw"
    """Depth images (16UC1 millimetres or 32FC1 metres)."""
    depth_type: Literal["image", "compressed"] = "image"
    """``image``: sensor_msgs/Image; ``compressed``: sensor_msgs/CompressedImage (compressedDepth)."""
    camera_info: str = "/camera/depth/camera_info"
    """The depth camera's sensor_msgs/CameraInfo (its K)."""
    odometry: str = ""
    """The vehicle's odometry; empty: /odom (nav_msgs) or /fmu/out/vehicle_odometry (px4)."""
    odometry_type: Literal["nav_msgs", "px4"] = "nav_msgs"
    """``nav_msgs``: nav_msgs/Odometry (ENU, FLU body); ``px4``: px4_msgs/VehicleOdometry (NED, FRD)."""
    tf: str = "/tf"
    tf_static: str = "/tf_static"
    clock: str = "/clock"
    """rosgraph_msgs/Clock, read when ``sim_time`` is on."""
    goal: str = "/goal_pose"
    """geometry_msgs/PoseStamped goals in the world frame (RViz's "2D Goal Pose" publishes here)."""
    sensor_qos: Literal["sensor", "reliable"] = "sensor"
    """QoS of depth, camera info and odometry: ``sensor`` (best effort, ROS's SensorDataQoS) also
    receives from reliable publishers."""
    px4_setpoint: str = "/fmu/in/trajectory_setpoint"
    px4_offboard: str = "/fmu/in/offboard_control_mode"
    setpoint: str = "/mapkit/setpoint"
    """trajectory_msgs/MultiDOFJointTrajectory with one point: the setpoint for other autopilots."""
    path: str = "/mapkit/path"
    """nav_msgs/Path of the reference ahead, for visualisation."""
    status: str = "/mapkit/status"
    """std_msgs/String: one JSON object per update (state, reason, goal, input ages)."""

    @property
    def odometry_topic(self) -> str:
        return self.odometry or {"nav_msgs": "/odom", "px4": "/fmu/out/vehicle_odometry"}[self.odometry_type]

    def validate(self) -> None:
        if self.odometry_type not in ODOMETRY_TYPES or self.depth_type not in DEPTH_TYPES:
            raise FlyError(f"topics.odometry_type {self.odometry_type!r} / depth_type {self.depth_type!r}: use one of "
                           f"{', '.join(ODOMETRY_TYPES)} / {', '.join(DEPTH_TYPES)}")
        dds_topic(self.odometry_topic)
        for name in ("depth", "camera_info", "tf", "tf_static", "clock", "goal", "px4_setpoint", "px4_offboard",
                     "setpoint", "path", "status"):
            dds_topic(getattr(self, name))
        if self.sensor_qos not in QOS_NAMES:
            raise FlyError(f"topics.sensor_qos {self.sensor_qos!r} is unknown; use sensor or reliable")


@dataclass(frozen=True)
class Frames:
    """Frame names (REP 105)."""

    world: str = "odom"
    """The world frame (ENU) of odometry, goals and the published path."""
    body: str = "base_link"
    """The vehicle's body frame (FLU); the camera mount is looked up in tf from here to the depth
    image's frame_id."""


@dataclass(frozen=True)
class FlyConfig:
    """Everything `mapkit fly` is told."""

    topics: Topics = field(default_factory=Topics)
    frames: Frames = field(default_factory=Frames)
    link: DdsConfig = field(default_factory=DdsConfig)
    pilot: PilotConfig = field(default_factory=PilotConfig)
    """The pilot's options; its ``frame_timeout`` is how long depth may stop before it brakes."""
    plan_lead: float = 0.1
    """Seconds ahead of the node's clock that the first plans are made for. Later plans lead by what
    planning and handing a plan to the setpoint stream took, measured (:attr:`FlyNode.plan_lead`: the
    median of the last 20 plans, plus 3 ms). The stream flies the previous reference until the
    new one's time, so the setpoints never jump (a jump in yaw makes a small quadrotor climb), and the
    plan takes over as soon as it can. A plan that arrives later than its time is counted in the status's ``late_plans``.
    (`mapkit eval` plans in simulated time that stands still while it plans: it needs no lead.)"""
    rate: float = 50.0
    """Hz of the setpoint stream (PX4 needs at least 2 Hz before and during offboard)."""
    px4: bool = True
    """Publish PX4's TrajectorySetpoint and OffboardControlMode (converted to NED)."""
    dry_run: bool = False
    """Plan and publish the path and status, but no setpoint at all."""
    odometry_timeout: float = 0.25
    """Seconds without odometry before braking from the reference (then holding)."""
    fence_radius: float = 20.0
    """Metres around the start (the first odometry) inside which goals are accepted."""
    fence_height: float = 5.0
    """Metres above and below the start inside which goals are accepted."""
    sim_time: bool = False
    """Run on the simulator's clock (/clock), as ROS's use_sim_time: timeouts, stamps and the reference
    follow it (a simulator slower than real time flies the same)."""
    max_stamp_skew: float = 0.5
    """Seconds a message's header stamp may differ from this machine's clock; a larger gap is logged and
    the receive time is used (unsynchronised clocks)."""
    record: Path | None = None
    """Write every input and output message to this MCAP file."""

    def validate(self) -> None:
        """Raise :class:`FlyError` naming the first option out of range."""
        self.topics.validate()
        self.pilot.validate()
        for name in ("rate", "odometry_timeout", "fence_radius", "fence_height", "max_stamp_skew"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value > 0):
                raise FlyError(f"{name} must be a finite number > 0, got {value}")
        if not 0.0 <= self.plan_lead < self.pilot.replan_interval:
            raise FlyError(f"plan_lead {self.plan_lead} s must be in [0, the pilot's replan_interval "
                           f"{self.pilot.replan_interval} s)")
        if self.rate < 2.0:
            raise FlyError(f"rate {self.rate} Hz is below the 2 Hz PX4 requires in offboard; use 20–100 Hz")
