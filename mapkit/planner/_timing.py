"""How a plan is timed, the same in training and in flight: the total time from a speed profile over
the key-point path, a minimum duration per segment, the split of the rest, and the end condition."""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Literal

import torch

from mapkit.trajopt import allocate_times, profile_time

if TYPE_CHECKING:
    from mapkit.planner._config import PlannerConfig
    from mapkit.trajopt import TimeAllocationNet

Allocation = Literal["tan", "gradient", "uniform", "poly5"]
"""How the time left after every segment's minimum is split (Table III of the paper)."""


@dataclass
class Timing:
    """Segment times of a batch of plans."""

    durations: torch.Tensor
    """(B, M) seconds, each >= the minimum segment time."""
    shares: torch.Tensor
    """(B, M) the split of the time above the minima (sum 1): ``durations = t_min + shares (total − M t_min)``."""
    total: torch.Tensor
    """(B,) seconds."""
    end: torch.Tensor
    """(B, 3, 3) end velocity / acceleration / jerk rows."""
    cruise_speed: torch.Tensor
    """(B,) m/s: the cruise speed of each plan's speed profile (the total-time rule's)."""
    decel: torch.Tensor
    """(B,) m/s²: the rate at which each plan's speed profile changes to the end speed."""


def end_state(waypoints: torch.Tensor, end_speed: torch.Tensor) -> torch.Tensor:
    """(B, 3, 3) end velocity / acceleration / jerk: ``end_speed`` (B,) m/s along the last segment."""
    last = waypoints[:, -1] - waypoints[:, -2]
    unit = last / last.norm(dim=-1, keepdim=True).clamp_min(1e-9)
    end = torch.zeros(waypoints.shape[0], 3, 3, dtype=waypoints.dtype, device=waypoints.device)
    end[:, 0] = end_speed.to(waypoints.dtype).reshape(-1, 1) * unit
    return end


@torch.no_grad()
def total_time(waypoints: torch.Tensor, start: torch.Tensor, end_speed: torch.Tensor, config: PlannerConfig,
               cruise_speed: torch.Tensor | None = None, decel: torch.Tensor | None = None) -> torch.Tensor:
    """(B,) seconds: the speed profile over the key-point path (:func:`mapkit.trajopt.profile_time`:
    from the start speed along the first segment to ``cruise_speed`` at ``accel``, then to
    ``end_speed``), at least ``min_total_time`` and M × ``min_segment_time``, at most
    ``max_total_time``; ``cruise_speed`` (B,) replaces the config's per plan (see :func:`turn_speed`),
    ``decel`` (B,) its ``accel`` for slowing down to the end speed. No gradient (the TAN learns the split)."""
    seg = waypoints[:, 1:] - waypoints[:, :-1]
    length = seg.norm(dim=-1).sum(-1)
    first = seg[:, 0] / seg[:, 0].norm(dim=-1, keepdim=True).clamp_min(1e-9)
    v_along = (start[:, 0].to(waypoints.dtype) * first).sum(-1)
    cruise = config.cruise_speed if cruise_speed is None else cruise_speed
    T = profile_time(length, v_along, end_speed, cruise_speed=cruise, accel=config.accel, decel=decel)
    floor = max(config.min_total_time, seg.shape[1] * config.min_segment_time)
    return T.to(waypoints.dtype).clamp(floor, config.max_total_time)


def turn_speed(waypoints: torch.Tensor, lateral_accel: float) -> torch.Tensor:
    """(B,) m/s at which the sharpest turn of each key-point path (B, M+1, 3) is flown at
    ``lateral_accel`` m/s²: √(a R) for the arc tangent to both segments of a turn at half the shorter
    one's length from the corner (R = that length / tan(turn angle / 2)); inf for a straight path."""
    seg = waypoints[:, 1:] - waypoints[:, :-1]
    length = seg.norm(dim=-1)
    if seg.shape[1] < 2:
        return torch.full(waypoints.shape[:1], float("inf"), dtype=waypoints.dtype, device=waypoints.device)
    unit = seg / length.unsqueeze(-1).clamp_min(1e-9)
    cos = (unit[:, :-1] * unit[:, 1:]).sum(-1).clamp(-1.0, 1.0)
    half = 0.5 * torch.arccos(cos)
    tangent = 0.5 * torch.minimum(length[:, :-1], length[:, 1:])
    # a turn of nearly 180° has a radius of nearly 0 (tan stays finite below π/2); a repeated
    # key-point has no direction, hence no turn
    turns = (half > 1e-9) & (tangent > 1e-9)
    radius = torch.where(turns, tangent / torch.tan(half.clamp(max=1.5)), torch.full_like(half, float("inf")))
    return torch.sqrt(lateral_accel * radius.min(dim=-1).values)


def durations_from_shares(shares: torch.Tensor, total: torch.Tensor, min_segment: float) -> torch.Tensor:
    """(B, M): every segment gets ``min_segment`` seconds, ``shares`` split the rest of ``total``."""
    M = shares.shape[-1]
    return min_segment + shares * (total.reshape(-1, 1) - M * min_segment)


def shares_from_durations(durations: torch.Tensor, min_segment: float) -> torch.Tensor:
    """Inverse of :func:`durations_from_shares` (the total is the durations' sum); an even split when
    the minima take all the time."""
    M = durations.shape[-1]
    free = durations.sum(-1, keepdim=True) - M * min_segment
    return torch.where(free > 1e-9, (durations - min_segment) / free.clamp_min(1e-9), torch.full_like(durations, 1.0 / M))


def plan_timing(waypoints: torch.Tensor, start: torch.Tensor, end_speed: torch.Tensor, config: PlannerConfig, *,
                allocation: Allocation = "tan", tan: TimeAllocationNet | None = None,
                gradient_iters: int = 30, cruise_speed: torch.Tensor | None = None,
                decel: torch.Tensor | None = None) -> Timing:
    """Segment times for waypoints (B, M+1, 3) from ``start`` (B, 3, 3) (velocity, acceleration,
    jerk) to ``end_speed`` (B,) m/s; ``tan`` is needed for ``allocation="tan"``; its shares keep
    their gradient (the caller detaches what the trajectory uses). ``cruise_speed`` (B,): each
    plan's own cruise speed instead of the config's, ``decel`` (B,) its rate of slowing down to the
    end speed (:func:`total_time`)."""
    t_min = config.min_segment_time
    total = total_time(waypoints, start, end_speed, config, cruise_speed, decel)
    end = end_state(waypoints, end_speed)
    profile = {name: (torch.full_like(total, default) if value is None else value.to(total.dtype).expand_as(total).clone())
               for name, value, default in (("cruise_speed", cruise_speed, config.cruise_speed),
                                            ("decel", decel, config.accel))}
    M = waypoints.shape[1] - 1
    if allocation == "tan":
        if tan is None:
            raise ValueError("allocation 'tan' needs the TimeAllocationNet")
        dtype = next(tan.parameters()).dtype
        if tan.config.boundary_inputs:
            shares = tan.shares(waypoints.to(dtype), start=start.to(dtype), end_speed=end_speed.to(dtype),
                                total_time=total.to(dtype))
        else:
            shares = tan.shares(waypoints.to(dtype))
        # A tiny floor: the softmax can underflow for a degenerate input.
        shares = shares.to(waypoints.dtype).clamp_min(1e-4)
        shares = shares / shares.sum(-1, keepdim=True)
        durations = durations_from_shares(shares.detach(), total, t_min)
        return Timing(durations=durations, shares=shares, total=total, end=end, **profile)
    if allocation == "uniform":
        durations = (total / M).reshape(-1, 1).expand(-1, M).clone()
    elif allocation == "poly5":
        durations = allocate_times(waypoints.detach(), "poly5", total_time=total).to(waypoints.dtype)
        durations = durations_from_shares(shares_from_durations(durations, 0.0).clamp_min(0.0), total, t_min)
    elif allocation == "gradient":
        durations = allocate_times(waypoints.detach().double(), "gradient", total_time=total.double(),
                                   start=start.double(), end=end.double(), min_duration=t_min,
                                   max_iters=gradient_iters).to(waypoints.dtype)
    else:
        raise ValueError(f"unknown allocation {allocation!r}")
    return Timing(durations=durations, shares=shares_from_durations(durations, t_min), total=total, end=end, **profile)
