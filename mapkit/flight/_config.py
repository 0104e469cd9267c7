"""The pilot's typed options and the vehicle state it is given."""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from mapkit.flight._errors import FlightError


@dataclass(frozen=True)
class PilotConfig:
    """How the pilot turns frames into a reference: replanning, braking, facing and the input checks."""

    replan_interval: float = 0.5
    """Seconds between plans: a frame sooner than this after the last plan only counts as a sign of
    life (the stack's layers were tuned replanning every 0.5 s)."""
    plan_latency: float = 0.02
    """Seconds from a frame's stamp to the new plan taking over (from the previous reference's state then)."""
    horizon: float = 6.0
    """Metres: the goal is clipped to this distance (a local goal along the way to the real goal; the
    network was trained on goals within the depth range) and plans pass it at cruise speed."""
    goal_radius: float = 0.5
    """Metres: within this of the goal the status is ``reached`` and the pilot stops replanning."""
    brake_deceleration: float = 3.0
    """m/s², about the peak deceleration of a brake to rest: it stops v² / this metres ahead."""
    look_ahead: float = 1.5
    """Seconds: while moving, the vehicle (and its camera) heads toward where the reference will be this
    much later instead of along its velocity, as a pilot looks into a turn (it sees the wall beside a
    doorway before it gets there). 0: along the velocity."""
    look_turn_deg: float = 60.0
    """Degrees a hovering vehicle turns to look elsewhere when no plan is accepted."""
    max_yaw_rate: float = 3.0
    """rad/s: the reference's yaw turns no faster than this."""
    max_yaw_accel: float = 12.0
    """rad/s²: nor speeds up or slows its turn faster than this (a quadrotor's yaw torque is small: a step
    in yaw saturates its rotors)."""
    frame_timeout: float = 0.5
    """Seconds without a depth frame after which the pilot brakes to rest and holds (status
    ``braking``, then ``blocked``) until frames come again."""
    pose_tolerance: float = 1.0
    """Metres: a frame whose pose lies farther than this from the vehicle's state is not planned from:
    the pilot brakes (odometry and the camera's pose disagree)."""
    resync_distance: float = 1.0
    """Metres: when the vehicle is farther than this from the reference, the reference is replaced by a
    brake from the vehicle's own state (it was pushed away, or another pilot flew it)."""

    def validate(self) -> None:
        """Raise :class:`FlightError` naming the first option out of range."""
        positive = {"replan_interval": self.replan_interval, "horizon": self.horizon, "goal_radius": self.goal_radius,
                    "brake_deceleration": self.brake_deceleration, "max_yaw_rate": self.max_yaw_rate,
                    "max_yaw_accel": self.max_yaw_accel,
                    "frame_timeout": self.frame_timeout, "pose_tolerance": self.pose_tolerance,
                    "resync_distance": self.resync_distance}
        for name, value in positive.items():
            if not (math.isfinite(value) and value > 0):
                raise FlightError(f"PilotConfig.{name} must be a finite number > 0, got {value}")
        for name, value in {"look_ahead": self.look_ahead, "look_turn_deg": self.look_turn_deg}.items():
            if not (math.isfinite(value) and value >= 0):
                raise FlightError(f"PilotConfig.{name} must be a finite number >= 0, got {value}")
        if not 0 <= self.plan_latency < self.replan_interval:
            raise FlightError(f"PilotConfig.plan_latency must be in [0, replan_interval {self.replan_interval} s), "
                              f"got {self.plan_latency}")


def finite_vector(value: object, name: str) -> np.ndarray:
    """``value`` as a finite float64 (3,) vector; :class:`FlightError` names a bad one."""
    try:
        out = np.asarray(value, dtype=np.float64).reshape(3)
    except (TypeError, ValueError):
        raise FlightError(f"{name} must be 3 numbers (x, y, z world frame, SI units), got {value!r}") from None
    if not np.all(np.isfinite(out)):
        raise FlightError(f"{name} {out.tolist()} is not finite: pass the vehicle's estimate, or stop calling "
                          "the pilot while it has none")
    return out


@dataclass
class VehicleState:
    """The vehicle's state estimate, world frame (ENU, z up), SI units."""

    position: np.ndarray
    """(3,) metres (the body's centre)."""
    velocity: np.ndarray = field(default_factory=lambda: np.zeros(3))
    """(3,) m/s."""
    acceleration: np.ndarray | None = None
    """(3,) m/s² when known (None: taken as zero where it is needed)."""
    yaw: float = 0.0
    """Radians from +x counter-clockwise: the heading of the body's x axis."""

    def __post_init__(self) -> None:
        self.position = finite_vector(self.position, "state.position")
        self.velocity = finite_vector(self.velocity, "state.velocity")
        if self.acceleration is not None:
            self.acceleration = finite_vector(self.acceleration, "state.acceleration")
        if not math.isfinite(float(self.yaw)):
            raise FlightError(f"state.yaw {self.yaw} is not finite: pass the heading in radians")
        self.yaw = float(self.yaw)

    def derivatives(self) -> np.ndarray:
        """(4, 3) position, velocity, acceleration (zero when unknown), jerk (zero)."""
        acc = np.zeros(3) if self.acceleration is None else self.acceleration
        return np.stack([self.position, self.velocity, acc, np.zeros(3)])
