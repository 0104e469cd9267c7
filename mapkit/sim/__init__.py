"""Simulated UAV depth recordings with exact ground truth.

- :func:`make_world`, :class:`World` and its primitives: seeded forest / office / garage worlds with
  an exact signed distance and analytic ray casting.
- :class:`CameraModel`, :func:`render_depth`: a D435-like depth camera (pixel-centre convention).
- :func:`plan_flight` → :class:`Flight`; :class:`FreeSpaceGraph`: paths through exact free space.
- :class:`SimConfig`, :func:`simulate`, :func:`render_flight`: the recording (bag + ``.world.json`` /
  ``.world.ply`` / ``.flight.npz``); :class:`BagRecorder`, :func:`output_path` from :mod:`mapkit.bags`.
"""

from mapkit.bags import BagRecorder, output_path
from mapkit.sim._camera import CameraModel, camera_extrinsics, render_depth
from mapkit.sim._errors import SimError
from mapkit.sim._flight import Flight, plan_flight
from mapkit.sim._procedural import DEFAULT_DENSITIES, DEFAULT_SIZES, MIN_SIZES, WORLD_KINDS, make_world
from mapkit.sim._search import FreeSpaceGraph
from mapkit.sim._simulate import (
    RenderedFlight,
    SimConfig,
    SimResult,
    ground_truth_paths,
    render_flight,
    simulate,
)
from mapkit.sim._world import Box, Capsule, Cylinder, HalfSpace, Primitive, World

__all__ = [
    "BagRecorder", "output_path",
    "Box", "Capsule", "Cylinder", "HalfSpace", "Primitive", "World",
    "WORLD_KINDS", "DEFAULT_SIZES", "DEFAULT_DENSITIES", "MIN_SIZES", "make_world",
    "CameraModel", "render_depth", "camera_extrinsics",
    "Flight", "plan_flight", "FreeSpaceGraph",
    "SimConfig", "SimResult", "RenderedFlight", "simulate", "render_flight", "ground_truth_paths",
    "SimError",
]
