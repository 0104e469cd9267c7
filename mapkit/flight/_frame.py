"""Planning from one recorded frame to a goal given in the body or the world frame: what `mapkit plan`
and the viewer's live planner both do."""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import ArrayLike, NDArray

from mapkit._choices import GOAL_FRAMES, GoalFrame
from mapkit.geometry import invert_transform

if TYPE_CHECKING:
    from mapkit.flight._single import Planner, PlanResult

__all__ = ["GOAL_FRAMES", "FramePlan", "GoalFrame", "goal_in_body", "plan_from_frame"]


def goal_in_body(goal: ArrayLike, T_world_body: NDArray[np.float64], frame: GoalFrame) -> NDArray[np.float64]:
    """A goal (3,) metres given in ``frame`` → the body frame of the pose ``T_world_body`` (4, 4)."""
    g = np.asarray(goal, dtype=np.float64).reshape(3)
    if frame == "body":
        return g
    T_body_world = invert_transform(T_world_body)
    return T_body_world[:3, :3] @ g + T_body_world[:3, 3]


@dataclass(frozen=True)
class FramePlan:
    """A plan from one frame, with the goal it was asked for in that frame's body frame."""

    goal_body: NDArray[np.float64]
    """(3,) metres: the goal asked for (before any clipping to the planner's range; see
    :attr:`PlanResult.goal_body` for the one planned to)."""
    result: PlanResult


def plan_from_frame(
    planner: Planner,
    depth: NDArray[np.float32],
    T_world_body: NDArray[np.float64],
    T_world_camera: NDArray[np.float64],
    K: NDArray[np.float64],
    goal: ArrayLike,
    *,
    goal_frame: GoalFrame = "body",
    velocity_body: NDArray[np.float64] | None = None,
    corridor: float | None = None,
    widen: tuple[float, ...] | None = None,
    shift: tuple[float, ...] | None = None,
) -> FramePlan:
    """Plan from one frame (depth (H, W) metres, its body and optical-camera poses (4, 4), K (3, 3)) to
    ``goal`` (3,) given in ``goal_frame``; ``velocity_body`` (3,), ``corridor``, ``widen`` and ``shift`` as
    in :meth:`Planner.plan` (None: its defaults, :data:`mapkit.flight.WIDEN` and :data:`~mapkit.flight.SHIFT`)."""
    goal_body = goal_in_body(goal, T_world_body, goal_frame)
    T_body_camera = invert_transform(T_world_body) @ T_world_camera
    from mapkit.flight._single import SHIFT, WIDEN  # torch is loaded by now: a planner exists

    result = planner.plan(depth, goal_body, velocity_body=velocity_body, corridor=corridor, K=K,
                          T_body_camera=T_body_camera, widen=WIDEN if widen is None else widen,
                          shift=SHIFT if shift is None else shift)
    return FramePlan(goal_body, result)
