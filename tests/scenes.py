"""Analytic scenes (box, sphere, plane) recorded as real MCAP flights for fuse → esdf tests."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from mapkit.bags import BagRecorder
from mapkit.sim import Box, CameraModel, Capsule, HalfSpace, World, camera_extrinsics, render_depth

T0 = 1_700_000_000_000_000_000


def box_world() -> World:
    """A 1 x 1 x 1 m box standing on a floor at z = 0, centred at (0, 0, 0.5)."""
    return World([Box((0.0, 0.0, 0.5), (0.5, 0.5, 0.5)), HalfSpace((0.0, 0.0, 1.0), 0.0)], bounds=[[-3, -3, 0], [3, 3, 2.5]])


def sphere_world() -> World:
    """A sphere of radius 0.6 m at (0, 0, 1.2) (a zero-length capsule) over a floor."""
    return World([Capsule((0.0, 0.0, 1.2), (0.0, 0.0, 1.2), 0.6), HalfSpace((0.0, 0.0, 1.0), 0.0)], bounds=[[-3, -3, 0], [3, 3, 2.5]])


def orbit_poses(n: int, *, radius: float = 2.5, height: float = 1.2, target: tuple[float, float, float] = (0, 0, 0.6)) -> list[np.ndarray]:
    """Body poses (FLU) on a circle, looking at `target`."""
    poses = []
    for i in range(n):
        a = 2 * np.pi * i / n
        p = np.array([radius * np.cos(a), radius * np.sin(a), height])
        fwd = np.asarray(target, float) - p
        fwd /= np.linalg.norm(fwd)
        left = np.cross([0, 0, 1.0], fwd)
        left /= np.linalg.norm(left)
        up = np.cross(fwd, left)
        T = np.eye(4)
        T[:3, :3] = np.stack([fwd, left, up], axis=1)
        T[:3, 3] = p
        poses.append(T)
    return poses


def record_scene(world: World, out: Path, poses: list[np.ndarray], *, width: int = 160, height: int = 120,
                 encoding: str = "32FC1", fps: float = 30.0) -> Path:
    """Render exact depth along `poses` and write an MCAP (odometry + tf_static + camera info)."""
    camera = CameraModel(width=width, height=height)
    T_base_link, T_link_optical = camera_extrinsics()
    T_body_camera = T_base_link @ T_link_optical
    with BagRecorder(out, "mcap") as bag:
        bag.write_tf_static(T0, [(T_base_link, "base_link", "camera_link"),
                                 (T_link_optical, "camera_link", "camera_depth_optical_frame")])
        for i, T_world_body in enumerate(poses):
            s = T0 + int(round(i * 1e9 / fps))
            bag.write_odometry("/odom", s, T_world_body, frame_id="world", child_frame_id="base_link")
            depth = render_depth(world, T_world_body @ T_body_camera, camera)
            bag.write_camera_info("/camera/depth/camera_info", s, camera.K, width, height, frame_id="camera_depth_optical_frame")
            bag.write_depth("/camera/depth/image_rect_raw", s, depth, frame_id="camera_depth_optical_frame", encoding=encoding)
        path = bag.path
    return path
