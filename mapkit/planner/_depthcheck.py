"""Each candidate path checked against the depth image it was planned from: a point in view is
compared with the nearest depth measured within the image of the robot's disc around it (in front:
seen free space; behind: occluded or inside). The judge reads these margins; never the map.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
import torch.nn.functional as F

from mapkit.planner._errors import PlannerError

POINTS_PER_SEGMENT = 3
"""Samples per key-point segment (the origin itself is not checked)."""
FEATURES_PER_POINT = 2
"""in view (0/1), and the margin (measured − path depth) / 2 m clipped to [−1, 1] (0 out of view)."""


@dataclass
class CameraInput:
    """The calibration the planner needs to look its paths up in the depth image (batched)."""

    intrinsics: torch.Tensor
    """(B, 4) fx / W, fy / H, (cx + 0.5) / W, (cy + 0.5) / H of the original W × H image (invariant to resizing)."""
    T_camera_body: torch.Tensor
    """(B, 4, 4) body (FLU) → optical camera frame."""

    @classmethod
    def from_calibration(cls, K: torch.Tensor | np.ndarray, width: int, height: int,
                         T_body_camera: torch.Tensor | np.ndarray) -> CameraInput:
        """From K (B, 3, 3) or (3, 3) pixels, the image size and T_body_camera (B, 4, 4) or (4, 4)."""
        K = torch.as_tensor(K, dtype=torch.float64)
        T = torch.as_tensor(T_body_camera, dtype=torch.float64)
        if K.shape[-2:] != (3, 3) or T.shape[-2:] != (4, 4):
            raise PlannerError(f"K must be (3, 3) and T_body_camera (4, 4), got {tuple(K.shape)} and {tuple(T.shape)}")
        K, T = K.reshape(-1, 3, 3), T.reshape(-1, 4, 4)
        intr = torch.stack([K[:, 0, 0] / width, K[:, 1, 1] / height, (K[:, 0, 2] + 0.5) / width,
                            (K[:, 1, 2] + 0.5) / height], dim=1)
        return cls(intrinsics=intr.float(), T_camera_body=torch.linalg.inv(T).float())

    def expand(self, batch: int) -> CameraInput:
        """The same camera for ``batch`` samples (a single calibration is broadcast)."""
        if self.intrinsics.shape[0] == batch:
            return self
        if self.intrinsics.shape[0] != 1:
            raise PlannerError(f"camera has {self.intrinsics.shape[0]} calibrations for a batch of {batch}")
        return CameraInput(self.intrinsics.expand(batch, 4), self.T_camera_body.expand(batch, 4, 4))

    def to(self, device: torch.device | str) -> CameraInput:
        return CameraInput(self.intrinsics.to(device), self.T_camera_body.to(device))


def path_points(candidates: torch.Tensor) -> torch.Tensor:
    """(B, M, K * POINTS_PER_SEGMENT, 3): points along origin → k1 → … → kK (end of each step)."""
    B, M, K, _ = candidates.shape
    wp = torch.cat([torch.zeros_like(candidates[:, :, :1]), candidates], dim=2)  # (B, M, K+1, 3)
    frac = torch.arange(1, POINTS_PER_SEGMENT + 1, dtype=candidates.dtype, device=candidates.device) / POINTS_PER_SEGMENT
    a, b = wp[:, :, :-1, None], wp[:, :, 1:, None]  # (B, M, K, 1, 3)
    return (a + (b - a) * frac[:, None]).reshape(B, M, K * POINTS_PER_SEGMENT, 3)


WINDOWS = (3, 7, 15, 31, 63)
"""Square windows (input pixels) of the nearest-depth pyramid; each path point reads the one closest
to the image size of the robot's disc at its depth."""


def _pyramid_schedule() -> list[tuple[bool, int]]:
    """(halve first, odd step) per level of :data:`WINDOWS`: each level pools the previous one (windows
    add up); windows wider than 16 pixels run on a half-resolution grid."""
    schedule, size, scale = [], 1, 1
    for k in WINDOWS:
        halve = k > 16 and scale == 1
        if halve:
            scale, size = 2, size // 2 + 1
        step = max(1, (k // scale) - size + 1) | 1
        size = size + step - 1
        schedule.append((halve, step))
    return schedule


def nearest_depth_pyramid(x: torch.Tensor) -> torch.Tensor:
    """(B, len(WINDOWS), h, w): the nearest depth / max_depth within each window around every pixel
    of the preprocessed depth ``x`` (B, 2, h, w); pixels without a return count as far. Separable
    min-pooling (:func:`_pyramid_schedule`); on the CPU in numpy (the same minima, several times faster)."""
    level = torch.where(x[:, 1:2] > 0.5, x[:, :1], torch.ones_like(x[:, :1]))
    if level.device.type == "cpu":
        return torch.from_numpy(_pyramid_numpy(level.detach().numpy()))
    return _pyramid_torch(level)


def _pyramid_torch(level: torch.Tensor) -> torch.Tensor:
    """:func:`nearest_depth_pyramid` of ``level`` (B, 1, h, w) with torch's pooling (any device)."""
    h, w = level.shape[-2:]
    levels, scale = [], 1
    for halve, step in _pyramid_schedule():
        if halve:
            level, scale = -F.max_pool2d(-level, 2, stride=2, ceil_mode=True), 2
        rows = -F.max_pool2d(-level, (step, 1), stride=1, padding=(step // 2, 0))
        level = -F.max_pool2d(-rows, (1, step), stride=1, padding=(0, step // 2))
        full = level if scale == 1 else level.repeat_interleave(2, dim=-2).repeat_interleave(2, dim=-1)[..., :h, :w]
        levels.append(full)
    return torch.cat(levels, dim=1)


def _running_min(a: np.ndarray, size: int, axis: int) -> np.ndarray:
    """Minimum over the centred window of odd ``size`` along ``axis``, edges repeated outward: minima
    of doubling spans, then two overlapping spans per window."""
    m = np.moveaxis(a, axis, 0)  # a view: slices along the first axis stay views
    n, half = m.shape[0], size // 2
    m = np.concatenate([np.repeat(m[:1], half, axis=0), m, np.repeat(m[-1:], half, axis=0)])
    span = 1
    while 2 * span <= size:
        m = np.minimum(m[:-span], m[span:])
        span *= 2
    return np.moveaxis(np.minimum(m[:n], m[size - span:size - span + n]), 0, axis)


def _pyramid_numpy(level: np.ndarray) -> np.ndarray:
    """:func:`nearest_depth_pyramid` of ``level`` (B, 1, h, w) in numpy (exactly the same minima)."""
    B, _, h, w = level.shape
    schedule = _pyramid_schedule()
    out = np.empty((B, len(schedule), h, w), dtype=level.dtype)
    for i, (halve, step) in enumerate(schedule):
        if halve:
            even = np.pad(level, ((0, 0), (0, 0), (0, h % 2), (0, w % 2)), constant_values=np.inf)
            rows = np.minimum(even[:, :, 0::2], even[:, :, 1::2])  # 2 × 2 blocks (a reduce over them is slower)
            level = np.minimum(rows[..., 0::2], rows[..., 1::2])
        level = _running_min(_running_min(level, step, axis=2), step, axis=3)
        if level.shape[2:] == (h, w):
            out[:, i] = level[:, 0]
        elif h % 2 == 0 and w % 2 == 0:  # each half-resolution pixel fills its 2 × 2 block, in place
            out[:, i].reshape(B, h // 2, 2, w // 2, 2)[:] = level[:, 0, :, None, :, None]
        else:
            out[:, i] = level[:, 0].repeat(2, axis=1).repeat(2, axis=2)[:, :h, :w]
    return out


def depth_margins(candidates: torch.Tensor, x: torch.Tensor, camera: CameraInput, *, max_depth: float,
                  robot_radius: float = 0.35, pyramid: torch.Tensor | None = None) -> torch.Tensor:
    """(B, M, P · FEATURES_PER_POINT) :func:`point_margins` of the points along every candidate's
    key-point path (B, M, K, 3), body frame. ``pyramid``: the candidates' own
    :func:`nearest_depth_pyramid` rows when already computed (several goals share an image)."""
    return point_margins(path_points(candidates), x, camera, max_depth=max_depth, robot_radius=robot_radius,
                         pyramid=pyramid)


def point_margins(pts: torch.Tensor, x: torch.Tensor, camera: CameraInput, *, max_depth: float,
                  robot_radius: float = 0.35, pyramid: torch.Tensor | None = None) -> torch.Tensor:
    """(B, M, P · FEATURES_PER_POINT) features of the points ``pts`` (B, M, P, 3), body frame, against
    the preprocessed depth ``x`` (B, 2, h, w): per point whether it is in view, and the nearest measured
    depth within the image of a disc of ``robot_radius`` around it minus its own depth (metres / 2,
    clipped to ±1; 0 out of view). Pixels without a return count as far."""
    B, M, _, _ = pts.shape
    _, w = x.shape[-2:]
    T = camera.T_camera_body.to(pts.dtype)
    pc = pts @ T[:, None, :3, :3].transpose(-1, -2) + T[:, None, None, :3, 3]
    z = pc[..., 2]
    safe_z = z.clamp_min(1e-3)
    intr = camera.intrinsics.to(pts.dtype)[:, None, None]
    u = intr[..., 0] * pc[..., 0] / safe_z + intr[..., 2]
    v = intr[..., 1] * pc[..., 1] / safe_z + intr[..., 3]
    in_view = (z > 0.1) & (u >= 0) & (u <= 1) & (v >= 0) & (v <= 1)
    pyramid = nearest_depth_pyramid(x) if pyramid is None else pyramid
    grid = torch.stack([2 * u - 1, 2 * v - 1], dim=-1).reshape(B, M * pts.shape[2], 1, 2)
    levels = F.grid_sample(pyramid, grid.to(pyramid.dtype), mode="bilinear", padding_mode="border",
                           align_corners=False).reshape(B, len(WINDOWS), M, -1) * max_depth  # (B, L, M, P)
    disc_px = 2 * robot_radius * intr[..., 0] * w / safe_z  # the disc's width in input pixels
    sizes = torch.tensor(WINDOWS, dtype=pts.dtype, device=pts.device)
    level = (disc_px[..., None].log() - sizes.log()).abs().argmin(dim=-1)  # (B, M, P)
    measured = levels.gather(1, level[:, None].to(torch.long)).squeeze(1)
    margin = torch.where(in_view, ((measured - z) / 2.0).clamp(-1.0, 1.0), torch.zeros_like(z))
    return torch.stack([in_view.to(pts.dtype), margin], dim=-1).flatten(2)


def image_points(depth: torch.Tensor, camera: CameraInput, *, max_depth: float, stride: int = 2) -> torch.Tensor:
    """(B, P, 3) body-frame points of every ``stride``-th pixel of ``depth`` (B, h, w): the network's input
    size, depth / ``max_depth`` (1 = no return); pixels without a return lie 1e6 m away, so a nearest-point
    search never finds them."""
    B, h, w = depth.shape
    rows = torch.arange(0, h, stride, dtype=depth.dtype, device=depth.device)
    cols = torch.arange(0, w, stride, dtype=depth.dtype, device=depth.device)
    z = depth[:, ::stride, ::stride] * max_depth  # (B, h', w')
    intr = camera.intrinsics.to(depth.dtype)[:, :, None, None]
    x = ((cols + 0.5) / w - intr[:, 2]) / intr[:, 0] * z
    y = ((rows[:, None] + 0.5) / h - intr[:, 3]) / intr[:, 1] * z
    cam = torch.stack([x, y, z], dim=-1).reshape(B, -1, 3)
    T = camera.T_camera_body.to(depth.dtype)  # body → camera: p_body = Rᵀ (p_cam − t)
    body = (cam - T[:, None, :3, 3]) @ T[:, :3, :3]
    return torch.where((z < max_depth * (1 - 1e-6)).reshape(B, -1, 1), body, torch.full_like(body, 1e6))


def seen_conflicts(paths: torch.Tensor, x: torch.Tensor, camera: CameraInput, *, max_depth: float,
                   robot_radius: float = 0.35, pyramid: torch.Tensor | None = None) -> torch.Tensor:
    """(B, M) how many points along each path (B, M, P, 3), body frame (the origin first implied), lie
    in view behind or within the robot's size of a measured surface (:func:`depth_margins`)."""
    f = depth_margins(paths, x, camera, max_depth=max_depth, robot_radius=robot_radius, pyramid=pyramid)
    f = f.reshape(*f.shape[:2], -1, FEATURES_PER_POINT)
    return ((f[..., 0] > 0.5) & (f[..., 1] < 0)).sum(-1)
