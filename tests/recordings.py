"""Tiny recordings with known truth, written by rosbags / mcap writers (through BagRecorder)."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from scipy.spatial.transform import Rotation

from mapkit.bags import BagRecorder
from mapkit.geometry import invert_transform

T0 = 1_700_000_000_000_000_000
FPS = 30.0
K = np.array([[50.0, 0, 31.5], [0, 50.0, 23.5], [0, 0, 1]])
W, H = 64, 48

# body (FLU) → camera optical: z_opt = x_body, x_opt = -y_body, y_opt = -z_body, 10 cm forward.
T_BODY_CAMERA = np.array(
    [[0, 0, 1, 0.10], [-1, 0, 0, 0.0], [0, -1, 0, 0.05], [0, 0, 0, 1]], dtype=np.float64
)
T_BODY_LINK = np.eye(4)
T_BODY_LINK[:3, 3] = [0.10, 0.0, 0.05]
T_LINK_OPTICAL = invert_transform(T_BODY_LINK) @ T_BODY_CAMERA


def rotation_angle(R: np.ndarray) -> float:
    """Angle (radians) of a 3x3 rotation."""
    return float(Rotation.from_matrix(R).magnitude())


def body_pose(t: float) -> np.ndarray:
    """A smooth, curving body trajectory (world ENU)."""
    T = np.eye(4)
    T[:3, :3] = Rotation.from_euler("zyx", [0.6 * t, 0.05 * np.sin(t), 0.03 * np.cos(2 * t)]).as_matrix()
    T[:3, 3] = [2.0 * np.cos(0.5 * t), 2.0 * np.sin(0.5 * t), 1.5 + 0.2 * t]
    return T


def depth_image(i: int) -> np.ndarray:
    """Deterministic depth in metres with invalid pixels (NaN)."""
    v, u = np.mgrid[0:H, 0:W]
    d = (1.0 + 0.01 * u + 0.02 * v + 0.1 * i).astype(np.float32)
    d[5:9, 10:20] = np.nan
    return d


@dataclass
class Recording:
    path: Path
    stamps_ns: list[int]
    T_world_body: list[np.ndarray]
    T_world_camera: list[np.ndarray]
    depth: list[np.ndarray]
    extra: dict[str, Any] = field(default_factory=dict)


def write_pose_message(bag: BagRecorder, kind: str, stamp: int, T: np.ndarray) -> None:
    """geometry_msgs/PoseStamped on /mavros/local_position/pose ("pose_stamped") or
    PoseWithCovarianceStamped (zero covariance) on /pose ("pose_cov"), in frame "map"."""
    topic, msgtype = {"pose_stamped": ("/mavros/local_position/pose", "geometry_msgs/msg/PoseStamped"),
                      "pose_cov": ("/pose", "geometry_msgs/msg/PoseWithCovarianceStamped")}[kind]
    pose = bag.pose_message(T)
    if kind == "pose_cov":
        pose = bag.typestore.types["geometry_msgs/msg/PoseWithCovariance"](pose=pose, covariance=np.zeros(36))
    header = bag.header(stamp, "map", topic=topic)
    bag.write_raw(topic, msgtype, bag.typestore.types[msgtype](header=header, pose=pose), stamp)


def write_recording(
    out: Path,
    fmt: str = "mcap",
    *,
    n: int = 10,
    encoding: str = "16UC1",
    compressed: bool = False,
    pose: str = "odometry",
    camera_info: bool = True,
    tf_static: bool = True,
    depth_topic: str = "/camera/depth/image_rect_raw",
    row_padding: int = 0,
    big_endian: bool = False,
    pose_offset_s: float = 0.0,
    pose_stride: int = 1,
    depth_fn: Any = depth_image,
) -> Recording:
    """Depth at 30 Hz; poses at 4x that rate (a sample at every depth stamp, exact truth)."""
    stamps = [T0 + int(round(i * 1e9 / FPS)) for i in range(n)]
    rec = Recording(Path(), stamps, [], [], [])
    events: list[tuple[int, int, Any]] = []  # (stamp, order, write) so the file is in time order
    with BagRecorder(out, fmt) as bag:
        rec.path = bag.path
        if tf_static:
            bag.write_tf_static(
                stamps[0] - 10_000_000,
                [(T_BODY_LINK, "base_link", "camera_link"), (T_LINK_OPTICAL, "camera_link", "camera_depth_optical_frame")],
            )
        pose_stamps = [T0 + int(round(j * 1e9 / (4 * FPS))) for j in range(-4, 4 * n + 4)][::pose_stride]
        def write_pose(ps_written: int, T: np.ndarray) -> None:
            if pose == "odometry":
                bag.write_odometry("/odom", ps_written, T, frame_id="world", child_frame_id="base_link")
            elif pose in ("pose_stamped", "pose_cov"):
                write_pose_message(bag, pose, ps_written, T)
            elif pose == "tf":
                # world → odom as a (constant) dynamic edge, odom → base_link moving.
                T_world_odom = np.eye(4)
                T_world_odom[:3, 3] = [1.0, -2.0, 0.0]
                bag.write_tf(ps_written, [(T_world_odom, "world", "odom"), (invert_transform(T_world_odom) @ T, "odom", "base_link")])

        for ps in pose_stamps:
            ps_written = ps + int(round(pose_offset_s * 1e9))
            T = body_pose((ps - T0) / 1e9)
            events.append((ps_written, 0, lambda s=ps_written, T=T: write_pose(s, T)))
        for i, s in enumerate(stamps):
            T_wb = body_pose((s - T0) / 1e9)
            rec.T_world_body.append(T_wb)
            rec.T_world_camera.append(T_wb @ T_BODY_CAMERA)
            d = depth_fn(i)
            rec.depth.append(d)
            if camera_info:
                events.append((s, 1, lambda s=s: bag.write_camera_info(
                    "/camera/depth/camera_info", s, K, W, H, frame_id="camera_depth_optical_frame")))
            if compressed:
                events.append((s, 2, lambda s=s, d=d: bag.write_compressed_depth(
                    depth_topic, s, d, frame_id="camera_depth_optical_frame", encoding=encoding)))
            else:
                events.append((s, 2, lambda s=s, d=d: bag.write_depth(
                    depth_topic, s, d, frame_id="camera_depth_optical_frame", encoding=encoding,
                    row_padding=row_padding, big_endian=big_endian)))
        for _, _, write in sorted(events, key=lambda e: (e[0], e[1])):
            write()
    return rec
