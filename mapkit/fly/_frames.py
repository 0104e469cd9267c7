"""ENU/FLU (mapkit, ROS REP 103) ↔ NED/FRD (PX4), converted here and nowhere else.

World: ENU (x east, y north, z up) ↔ NED (x north, y east, z down): swap x and y, negate z; the map is
its own inverse. Body: FLU ↔ FRD: negate y and z. Yaw: ENU's is counter-clockwise from east, NED's
clockwise from north, so ψ_ned = π/2 − ψ_enu (and yaw rates change sign). PX4 writes quaternions w, x,
y, z; mapkit's are x, y, z, w.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.spatial.transform import Rotation

R_NED_ENU = np.array([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, -1.0]])
R_FLU_FRD = np.diag([1.0, -1.0, -1.0])


def enu_to_ned(v: ArrayLike) -> NDArray[np.float64]:
    """A world-frame vector (position, velocity, …; shape (..., 3)) from ENU to NED."""
    return np.asarray(v, dtype=np.float64) @ R_NED_ENU.T


def ned_to_enu(v: ArrayLike) -> NDArray[np.float64]:
    """A world-frame vector from NED to ENU (the same swap: the map is its own inverse)."""
    return np.asarray(v, dtype=np.float64) @ R_NED_ENU.T


def wrap(angle: float) -> float:
    """`angle` in [-π, π)."""
    return float((angle + np.pi) % (2 * np.pi) - np.pi)


def yaw_enu_to_ned(yaw: float) -> float:
    """Heading from ENU (CCW from east) to NED (CW from north), in [-π, π)."""
    return wrap(np.pi / 2 - yaw)


def yaw_ned_to_enu(yaw: float) -> float:
    """Heading from NED to ENU, in [-π, π)."""
    return wrap(np.pi / 2 - yaw)


def R_world_body_from_px4(q_wxyz: ArrayLike) -> NDArray[np.float64]:
    """The body (FLU) → world (ENU) rotation of PX4's attitude quaternion (FRD → NED, w x y z)."""
    w, x, y, z = np.asarray(q_wxyz, dtype=np.float64)
    R_ned_frd = Rotation.from_quat([x, y, z, w]).as_matrix()
    return R_NED_ENU.T @ R_ned_frd @ R_FLU_FRD


def px4_quaternion(R_world_body: ArrayLike) -> NDArray[np.float64]:
    """PX4's attitude quaternion (FRD → NED, w x y z) of a body (FLU) → world (ENU) rotation."""
    R_ned_frd = R_NED_ENU @ np.asarray(R_world_body, dtype=np.float64) @ R_FLU_FRD
    x, y, z, w = Rotation.from_matrix(R_ned_frd).as_quat()
    return np.array([w, x, y, z])
