"""Simulated UAV depth recordings with exact ground truth.

Public API:

- :func:`make_world`, :class:`World` (+ primitives :class:`Box`, :class:`Cylinder`,
  :class:`Capsule`, :class:`HalfSpace`): procedural forest / office / garage worlds with an exact
  signed distance and analytic ray casting.
- :class:`CameraModel`, :func:`render_depth`: a D435-like depth camera (pixel-centre convention).
- :func:`plan_flight`: a smooth, collision-checked flight through a world.
- :class:`SimConfig`, :func:`simulate`, :func:`render_flight`, :class:`SimResult`: the whole
  recording (bag + ``.world.json`` / ``.world.ply`` / ``.flight.npz``).
- :class:`BagRecorder`: write depth / camera_info / odometry / tf messages to mcap, rosbag2 or
  ROS1 bags without ROS.
- :class:`SimError`: every user-facing problem, in one line.
"""

from mapkit.sim.camera import CameraModel, apply_realsense_noise, camera_extrinsics, render_depth
from mapkit.sim.errors import SimError
from mapkit.sim.flight import Trajectory, plan_flight
from mapkit.sim.record import BagRecorder, output_path
from mapkit.sim.simulate import (
    BODY_FRAME,
    CAMERA_INFO_TOPIC,
    CAMERA_LINK_FRAME,
    DEPTH_TOPIC,
    ODOM_TOPIC,
    OPTICAL_FRAME,
    WORLD_FRAME,
    RenderedFlight,
    SimConfig,
    SimResult,
    ground_truth_paths,
    render_flight,
    simulate,
)
from mapkit.sim.world import Box, Capsule, Cylinder, HalfSpace, World
from mapkit.sim.worlds import WORLD_KINDS, make_world

__all__ = [
    "BagRecorder", "output_path",
    "Box", "Capsule", "Cylinder", "HalfSpace", "World", "WORLD_KINDS", "make_world",
    "CameraModel", "render_depth", "apply_realsense_noise", "camera_extrinsics",
    "Trajectory", "plan_flight",
    "SimConfig", "SimResult", "RenderedFlight", "simulate", "render_flight", "ground_truth_paths",
    "DEPTH_TOPIC", "CAMERA_INFO_TOPIC", "ODOM_TOPIC", "WORLD_FRAME", "BODY_FRAME", "CAMERA_LINK_FRAME",
    "OPTICAL_FRAME",
    "SimError",
]
