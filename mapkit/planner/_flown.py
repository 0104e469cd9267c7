"""What the flown-path judge reads (``PlannerConfig.flown_samples``): points along the first metres of
each candidate's trajectory as flown (which cuts the key-points' corners), and how far each lies from
the nearest point the depth image shows.
"""

from __future__ import annotations

import torch

from mapkit.planner._depthcheck import CameraInput, image_points, point_margins
from mapkit.trajopt import Trajectory

FLOWN_FEATURES = 3
"""Features per point of the flown-path head (:func:`flown_features`)."""
CLEARANCE_CAP = 3.0
"""Metres: clearances are capped here (as good as clear for a judge of the next metre or two)."""


def arclength_points(trajectory: Trajectory, *, horizon: float, count: int, dense: int = 96
                     ) -> tuple[torch.Tensor, torch.Tensor]:
    """((B, count, 3) points at the arc lengths ``horizon · i / count``, i = 1..count, along each
    trajectory (its end repeated past it), (B,) each one's length within ``horizon``), metres; arc
    length measured on ``dense`` time samples."""
    total = trajectory.durations.sum(-1).reshape(-1, 1)
    t = total * torch.linspace(0.0, 1.0, dense + 1, dtype=total.dtype, device=total.device)
    pos = trajectory.position(t).reshape(total.shape[0], dense + 1, 3)
    step = (pos[:, 1:] - pos[:, :-1]).norm(dim=-1)
    along = torch.cat([torch.zeros_like(step[:, :1]), step.cumsum(-1)], dim=1)  # (B, dense + 1)
    wanted = horizon * torch.arange(1, count + 1, dtype=pos.dtype, device=pos.device) / count
    wanted = wanted.expand(pos.shape[0], count).contiguous()
    hi = torch.searchsorted(along, wanted).clamp(1, dense)
    s0, s1 = along.gather(1, hi - 1), along.gather(1, hi)
    frac = ((wanted - s0) / (s1 - s0).clamp_min(1e-12)).clamp(0.0, 1.0)[..., None]
    p0 = pos.gather(1, (hi - 1)[..., None].expand(-1, -1, 3))
    p1 = pos.gather(1, hi[..., None].expand(-1, -1, 3))
    return p0 + frac * (p1 - p0), along[:, -1].clamp(max=horizon)


def input_points(x: torch.Tensor, camera: CameraInput, *, max_depth: float, stride: int = 2) -> torch.Tensor:
    """(B, P, 3) body-frame points of every ``stride``-th pixel of the preprocessed depth ``x``
    (B, 2, h, w); pixels without a measurement lie 1e6 m away (:func:`image_points`)."""
    # a pixel no valid source pixel reached (mask 0) holds no measurement: count it as no return
    depth = torch.where(x[:, 1] > 0.5, x[:, 0], torch.ones_like(x[:, 0]))
    return image_points(depth, camera.expand(x.shape[0]).to(x.device), max_depth=max_depth, stride=stride)


def flown_clearance(points: torch.Tensor, x: torch.Tensor, camera: CameraInput, *, max_depth: float,
                    stride: int = 2, recent: torch.Tensor | None = None) -> torch.Tensor:
    """(B, M, N) metres from each point (B, M, N, 3), body frame, to the nearest point of the
    preprocessed depth image ``x`` (B, 2, h, w) (every ``stride``-th pixel with a valid return) or of
    ``recent`` (B, P, 3), points of earlier frames in the same body frame, capped at
    :data:`CLEARANCE_CAP`. What the camera does not see counts as free."""
    B, M, N, _ = points.shape
    cloud = input_points(x, camera, max_depth=max_depth, stride=stride)
    if recent is not None:
        cloud = torch.cat([cloud, recent.to(cloud)], dim=1)
    # pixels without a return lie 1e6 m away: the matrix-product distance would lose the near ones
    d = torch.cdist(points.reshape(B, M * N, 3).to(cloud.dtype), cloud,
                    compute_mode="donot_use_mm_for_euclid_dist").amin(-1)
    return d.reshape(B, M, N).clamp(max=CLEARANCE_CAP)


def flown_features(points: torch.Tensor, x: torch.Tensor, camera: CameraInput, *, max_depth: float,
                   pyramid: torch.Tensor | None = None, recent: torch.Tensor | None = None) -> torch.Tensor:
    """(B, M, N, FLOWN_FEATURES) what the flown-path head reads at each point (B, M, N, 3), body frame,
    of the preprocessed depth ``x`` (B, 2, h, w): its :func:`flown_clearance` / :data:`CLEARANCE_CAP`,
    and :func:`point_margins` (in view; in front of (+) or behind (−) the measured surface)."""
    B, M, N, _ = points.shape
    near = flown_clearance(points, x, camera, max_depth=max_depth, recent=recent) / CLEARANCE_CAP
    seen = point_margins(points.to(x.dtype), x, camera.expand(B).to(x.device), max_depth=max_depth,
                         pyramid=pyramid).reshape(B, M, N, 2)
    return torch.cat([near.to(seen.dtype)[..., None], seen], dim=-1)
