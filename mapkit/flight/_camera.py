"""The camera contract: which depth images a model can fly from, and the camera of each frame relative
to the level frame the network plans in. Any resolution works whose normalised intrinsics match the
recorded camera's (:class:`~mapkit.flight.RunCamera`) within :data:`FOV_TOLERANCE` and
:data:`CENTRE_TOLERANCE`; another field of view is refused with the fix.
"""

from __future__ import annotations

import math

import numpy as np

from mapkit.flight._errors import FlightError
from mapkit.flight._plan import level_pose
from mapkit.flight._recorded import RunCamera
from mapkit.planner import CameraInput

FOV_TOLERANCE = 0.05
"""Largest relative difference of fx / W or fy / H from the recorded camera's."""
CENTRE_TOLERANCE = 0.05
"""Largest difference of the principal point from the recorded one, as a fraction of the image size."""
LEVEL_LIMIT_DEG = 80.0
"""A camera pitched more steeply than this has no heading to plan along."""


def check_intrinsics(K: np.ndarray, width: int, height: int, recorded: RunCamera | None) -> np.ndarray:
    """``K`` (3, 3) as float64, checked against the recorded camera (any K without one)."""
    try:
        K = np.array(K, dtype=np.float64).reshape(3, 3)  # a copy: callers may pass read-only arrays
    except (TypeError, ValueError):
        raise FlightError(f"K must be the (3, 3) pinhole matrix of the depth image, got {K!r}") from None
    if not (np.all(np.isfinite(K)) and K[0, 0] > 0 and K[1, 1] > 0):
        raise FlightError(f"K {K.tolist()} is not a pinhole matrix: fx and fy must be finite and > 0 pixels")
    if recorded is None:
        return K
    ours = _normalised(K, width, height)
    theirs = _normalised(recorded.K, recorded.width, recorded.height)
    focal_off = np.abs(ours[:2] / theirs[:2] - 1.0).max()
    centre_off = np.abs(ours[2:] - theirs[2:]).max()
    if focal_off > FOV_TOLERANCE or centre_off > CENTRE_TOLERANCE:
        raise FlightError(
            f"depth {width}x{height} with fx={K[0, 0]:.1f}, fy={K[1, 1]:.1f} sees {_fov(K, width, height)}, but the "
            f"model was trained on {_fov(recorded.K, recorded.width, recorded.height)} ({recorded.width}x{recorded.height}, "
            f"fx={recorded.K[0, 0]:.1f}): crop or resize the image (and K) to that field of view, or fine-tune "
            "the model on this camera")
    return K


def _normalised(K: np.ndarray, width: int, height: int) -> np.ndarray:
    """fx / W, fy / H, (cx + 0.5) / W, (cy + 0.5) / H (pixel centres at integers)."""
    return np.array([K[0, 0] / width, K[1, 1] / height, (K[0, 2] + 0.5) / width, (K[1, 2] + 0.5) / height])


def _fov(K: np.ndarray, width: int, height: int) -> str:
    """'86.0° × 67.4°': the horizontal and vertical field of view."""
    h = 2 * math.degrees(math.atan(width / (2 * K[0, 0])))
    v = 2 * math.degrees(math.atan(height / (2 * K[1, 1])))
    return f"{h:.1f}° × {v:.1f}°"


def planning_frame(position: np.ndarray, T_world_camera: np.ndarray, T_world_body: np.ndarray | None) -> np.ndarray:
    """(4, 4) the level frame the network plans in: at ``position``, heading along the body's x axis
    (``T_world_body``), else along the camera's optical axis, both projected on the horizontal plane."""
    axis = T_world_body[:3, 0] if T_world_body is not None else T_world_camera[:3, 2]
    horizontal = math.hypot(axis[0], axis[1])
    if horizontal < math.cos(math.radians(LEVEL_LIMIT_DEG)) * float(np.linalg.norm(axis)):
        what = "body's x axis" if T_world_body is not None else "camera's optical axis"
        raise FlightError(f"the {what} points {math.degrees(math.atan2(axis[2], horizontal)):+.0f}° from level: "
                          f"the pilot plans along a heading within {LEVEL_LIMIT_DEG:.0f}° of level; check the pose's "
                          "frames (world ENU z up, body FLU, camera optical z forward)")
    return level_pose(position, math.atan2(axis[1], axis[0]))


def frame_camera(K: np.ndarray, width: int, height: int, T_world_plan: np.ndarray,
                 T_world_camera: np.ndarray) -> CameraInput:
    """The frame's camera for the network: ``K`` and the camera's pose in the planning frame."""
    T_plan_camera = np.linalg.inv(T_world_plan) @ T_world_camera
    return CameraInput.from_calibration(K, width, height, T_plan_camera)


def rigid(T: object, name: str) -> np.ndarray:
    """``T`` as a finite (4, 4) rigid transform; :class:`FlightError` names a bad one."""
    try:
        out = np.asarray(T, dtype=np.float64).reshape(4, 4)
    except (TypeError, ValueError):
        raise FlightError(f"{name} must be a (4, 4) transform (T_a_b maps points from b into a), got {T!r}") from None
    if not np.all(np.isfinite(out)):
        raise FlightError(f"{name} is not finite: pass the pose estimate of this frame, or skip the frame")
    R = out[:3, :3]
    if not (np.allclose(R @ R.T, np.eye(3), atol=1e-3) and abs(np.linalg.det(R) - 1.0) < 1e-3
            and np.allclose(out[3], [0, 0, 0, 1])):
        raise FlightError(f"{name} is not a rigid transform (its rotation is not orthonormal with det +1, or its "
                          "last row is not 0 0 0 1): pass a 4x4 pose matrix")
    return out
