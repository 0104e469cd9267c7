"""What a planner gets at a planning instant and what it answers: the interface between the
:class:`~mapkit.flight.Pilot` and the planner it flies (the learned planner under its stack, or a
baseline of ``mapkit eval``)."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Protocol

import numpy as np

from mapkit.flight._pieces import Pieces
from mapkit.planner import CameraInput


@dataclass
class Observation:
    """What a method gets at a planning instant."""

    t: float
    """Time the plan takes over (the depth frame is ``plan_latency`` older), seconds."""
    T_world_body: np.ndarray
    """(4, 4) level pose at the depth frame: the frame the network plans in."""
    state_world: np.ndarray
    """(4, 3) position, velocity, acceleration, jerk the plan starts from at ``t`` (the reference's),
    world frame."""
    goal_world: np.ndarray
    """(3,) the real goal."""
    local_goal_body: np.ndarray
    """(3,) the goal in the body frame, clipped to the horizon."""
    depth: np.ndarray | None
    """(H, W) metres, NaN invalid (None for methods without a camera)."""
    goal_clipped: bool = False
    """True when the real goal lies beyond the horizon: the plan passes the local goal at cruise speed."""
    reference: Pieces | None = None
    """The reference being flown."""
    camera: CameraInput | None = None
    """The depth camera of this frame relative to ``T_world_body``; None: the method's own fixed camera."""

    def start_body(self) -> np.ndarray:
        """(4, 3) the start state in the body frame of the depth frame."""
        R, p = self.T_world_body[:3, :3], self.T_world_body[:3, 3]
        out = self.state_world @ R
        out[0] = R.T @ (self.state_world[0] - p)
        return out


@dataclass
class MethodPlan:
    """A method's answer."""

    pieces: Pieces
    """World-frame reference starting at the observation's time."""
    latency_ms: float
    """Wall-clock planning time (observation → trajectory)."""
    eta: float | None = None
    """Predicted collision probability, for methods that have one."""
    keypoints_world: np.ndarray | None = None
    """(K, 3) the key-points the trajectory passes, world frame (for plots)."""
    allocation_ms: float | None = None
    """Wall-clock time of the time allocation alone (TAN vs gradient descent)."""
    overrides_eta: bool = False
    """The method asks to fly this plan although η >= 0.5 (the reference being flown is no safer)."""
    brake_direction: np.ndarray | None = None
    """(3,) unit vector, body frame at the observation: where a blocked method brakes to (None: along
    the velocity)."""
    turn_side: float | None = None
    """+1 (counter-clockwise) or −1: the way a blocked hovering vehicle turns to look elsewhere (None: as last)."""
    look_at: np.ndarray | None = None
    """(3,) world point a hovering vehicle faces at the next observation (None: the goal)."""
    candidate: int | None = None
    """Which of the network's candidates the plan flies (None: none of them, or no network)."""
    within_limits: bool = True
    """False when the plan breaks the speed profile's limits even flown slower (the pilot keeps the last)."""
    blocked: bool = False
    """The method found no way ahead: the loop brakes to rest and turns to look elsewhere, whatever η says."""


class Method(Protocol):
    """A planner under evaluation."""

    name: str
    needs_depth: bool
    replans: bool

    def plan(self, obs: Observation) -> MethodPlan: ...


def level_pose(position: np.ndarray, yaw: float) -> np.ndarray:
    """(4, 4) T_world_body of a level body at ``position`` heading ``yaw`` (radians from +x)."""
    c, s = math.cos(yaw), math.sin(yaw)
    T = np.eye(4)
    T[:3, :3] = [[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]]
    T[:3, 3] = position
    return T

