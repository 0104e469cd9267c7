"""Rigid-transform helpers shared by every stage (4x4 float64 ``T_a_b``, quaternions ``xyzw``)."""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

__all__ = ["matrix_from_quat_xyzw", "quat_xyzw_from_matrix", "transform_from_pose", "invert_transform", "slerp_xyzw",
           "interpolate_transform"]


def matrix_from_quat_xyzw(q_xyzw: ArrayLike) -> NDArray[np.float64]:
    """3x3 rotation matrix of a unit quaternion (x, y, z, w); normalised first."""
    x, y, z, w = np.asarray(q_xyzw, dtype=np.float64) / np.linalg.norm(q_xyzw)
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
        ]
    )


def quat_xyzw_from_matrix(R: ArrayLike) -> NDArray[np.float64]:
    """Unit quaternion (x, y, z, w), w >= 0, of a rotation: a 3x3 matrix or the rotation block of a 4x4.

    scipy's conversion, because every recording :class:`mapkit.bags.BagRecorder` writes carries its
    bytes (a hand-written Shepperd's method differs in the last bit for most rotations).

    >>> quat_xyzw_from_matrix(np.diag([-1.0, -1.0, 1.0]))  # 180° about z
    array([0., 0., 1., 0.])
    >>> quat_xyzw_from_matrix(transform_from_pose([1.0, 2.0, 0.5], [0.0, 0.0, 0.6, 0.8])).round(12)
    array([0. , 0. , 0.6, 0.8])
    """
    from scipy.spatial.transform import Rotation

    q: NDArray[np.float64] = Rotation.from_matrix(np.asarray(R, dtype=np.float64)[:3, :3]).as_quat()
    # One fixed sign (w >= 0) so repeated writes of the same pose give identical bytes.
    return -q if q[3] < 0 else q


def transform_from_pose(translation: ArrayLike, q_xyzw: ArrayLike) -> NDArray[np.float64]:
    """4x4 transform from a translation and a quaternion (x, y, z, w)."""
    T = np.eye(4)
    T[:3, :3] = matrix_from_quat_xyzw(q_xyzw)
    T[:3, 3] = translation
    return T


def invert_transform(T: ArrayLike) -> NDArray[np.float64]:
    """Inverse of a rigid 4x4 transform (or a stack [..., 4, 4]).

    A body at (1, 2, 0.5) m yawed 90° (x forward, so its front is world +y); the world point
    (1, 3, 0.5) lies 1 m in front of it:

    >>> T_world_body = transform_from_pose([1.0, 2.0, 0.5], [0.0, 0.0, np.sqrt(0.5), np.sqrt(0.5)])
    >>> (invert_transform(T_world_body) @ [1.0, 3.0, 0.5, 1.0]).round(12) + 0.0
    array([1., 0., 0., 1.])
    >>> np.allclose(invert_transform(T_world_body) @ T_world_body, np.eye(4))
    True
    """
    T = np.asarray(T, dtype=np.float64)
    R_t = np.swapaxes(T[..., :3, :3], -1, -2)
    out = np.zeros_like(T)
    out[..., :3, :3] = R_t
    out[..., :3, 3] = -(R_t @ T[..., :3, 3, None])[..., 0]
    out[..., 3, 3] = 1.0
    return out


def slerp_xyzw(q0: NDArray[np.float64], q1: NDArray[np.float64], s: float) -> NDArray[np.float64]:
    """Spherical linear interpolation between unit quaternions, s in [0, 1], shortest arc."""
    dot = float(np.dot(q0, q1))
    if dot < 0.0:
        q1, dot = -q1, -dot
    if dot > 0.9995:  # nearly parallel: normalised lerp is exact to float precision here
        q = q0 + s * (q1 - q0)
        q_unit: NDArray[np.float64] = q / np.linalg.norm(q)
        return q_unit
    theta = np.arccos(dot)
    sin_theta = np.sin(theta)
    q_arc: NDArray[np.float64] = (np.sin((1.0 - s) * theta) * q0 + np.sin(s * theta) * q1) / sin_theta
    return q_arc


def interpolate_transform(
    t0: NDArray[np.float64],
    q0: NDArray[np.float64],
    t1: NDArray[np.float64],
    q1: NDArray[np.float64],
    s: float,
) -> NDArray[np.float64]:
    """Pose at fraction s between two poses: linear translation, slerp rotation."""
    return transform_from_pose(t0 + s * (t1 - t0), slerp_xyzw(q0, q1, s))
