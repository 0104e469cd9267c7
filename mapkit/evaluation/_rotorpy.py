"""A third-party quadrotor for closed-loop evaluation: rotorpy's :class:`Multirotor` (rigid body, first-order
rotor dynamics, parasitic and rotor drag) flown by rotorpy's geometric :class:`SE3Control`, behind a small
typed wrapper (`mapkit eval --vehicle rotorpy`).

rotorpy's conventions (``rotorpy.vehicles.multirotor``, checked by tests/test_rotorpy_vehicle.py) are
mapkit's own, so nothing is converted: world z up (ENU); body FLU with thrust along body +z and body x
the nose; ``state['q']`` the body → world rotation as ``xyzw``; ``state['w']`` the body rate (rad/s).
A flight second costs about 0.15 s of one core (one ``solve_ivp`` per step). ``Multirotor.step`` draws
from numpy's *global* RNG on every step (mapkit uses its own generators).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from math import ceil
from typing import Any

import numpy as np
from numpy.typing import NDArray

from mapkit.flight import Setpoint
from mapkit.geometry import matrix_from_quat_xyzw, transform_from_pose

__all__ = ["RATE_HZ", "RotorpyConfig", "RotorpyVehicle", "VehicleTrace"]

RATE_HZ = 100.0
"""Control and integration rate: SE3Control's command is held for each step, and slower than 100 Hz its
attitude loop (gain 544) goes unstable."""


@dataclass(frozen=True)
class RotorpyConfig:
    """How the rotorpy vehicle (rotorpy's 0.5 kg hummingbird) is simulated."""

    drag_feedforward: bool = True
    """Add the rotor drag the airframe meets at the reference's velocity (rotorpy's own model, rotors at
    hover speed) to the acceleration fed forward: SE3Control compensates no drag, so the vehicle
    otherwise lags its reference along the track."""


def _as_rotorpy(setpoint: Setpoint, drag: np.ndarray | None) -> dict[str, Any]:
    """The ``flat_output`` dict rotorpy's controllers take (SE3Control feeds the acceleration forward and
    reads yaw and yaw rate; jerk and snap are passed on), with ``drag`` (3, 3: linear drag per unit
    velocity over mass; None: none) compensated in the acceleration."""
    acceleration = setpoint.acceleration if drag is None else setpoint.acceleration + drag @ setpoint.velocity
    return {"x": setpoint.position, "x_dot": setpoint.velocity, "x_ddot": acceleration,
            "x_dddot": setpoint.jerk, "x_ddddot": setpoint.snap, "yaw": setpoint.yaw, "yaw_dot": setpoint.yaw_rate}


@dataclass
class VehicleTrace:
    """One call to :meth:`RotorpyVehicle.fly`: samples after each integration step, the end time
    included, the start excluded. World frame (ENU), SI units."""

    t: np.ndarray
    """(N,) seconds, increasing; ``t[-1]`` is ``fly``'s ``t1``."""
    position: np.ndarray
    """(N, 3) metres, the vehicle's centre of mass."""
    velocity: np.ndarray
    """(N, 3) m/s."""
    acceleration: np.ndarray
    """(N, 3) m/s², from the dynamics at each sample (thrust, gravity, drag over mass)."""
    quaternion_xyzw: np.ndarray
    """(N, 4) body → world attitude, scalar last, w >= 0."""
    reference: np.ndarray
    """(N, 3) metres, the reference position at ``t`` (tracking error: ``position - reference``)."""


class RotorpyVehicle:
    """rotorpy's Multirotor under rotorpy's SE3Control, zero wind; see the module docstring for frames.

    >>> vehicle = RotorpyVehicle()  # doctest: +SKIP
    >>> vehicle.reset(np.array([0.0, 0.0, 1.0]), yaw=0.0)  # doctest: +SKIP
    >>> trace = vehicle.fly(reference.sample, 0.0, 1.0)  # a mapkit.flight.Reference  # doctest: +SKIP
    """

    def __init__(self, config: RotorpyConfig = RotorpyConfig()) -> None:
        # imported here: `mapkit.evaluation` stays fast to import for the default tracker
        from rotorpy.controllers.quadrotor_control import SE3Control
        from rotorpy.vehicles.hummingbird_params import quad_params
        from rotorpy.vehicles.multirotor import Multirotor

        self.config = config
        self._params = dict(quad_params)  # a copy: rotorpy's dict is module state
        self._g = 9.81  # rotorpy's value (Multirotor.g)
        # Each rotor carries a 1/num_rotors share of the weight: k_eta ω² = m g / n.
        p = self._params
        self._hover_speed = float(np.sqrt(p["mass"] * self._g / (p["num_rotors"] * p["k_eta"])))
        self._controller = SE3Control(self._params)
        # rotor drag (each rotor's hub force −ω k v, ω at hover) per unit velocity over the mass; the
        # parasitic drag c_D |v| v is left out: at the pace flown it is a hundredth of it
        self._drag = (p["num_rotors"] * self._hover_speed * np.diag([p["k_d"], p["k_d"], p["k_z"]]) / p["mass"]
                      if config.drag_feedforward else None)
        self._state: dict[str, NDArray[np.float64]] = self._rest_state(np.zeros(3), 0.0)
        self._multirotor = Multirotor(self._params, initial_state=self._state, control_abstraction="cmd_motor_speeds")
        self._acceleration = np.zeros(3)

    def _rest_state(self, position: NDArray[np.float64], yaw: float) -> dict[str, NDArray[np.float64]]:
        """rotorpy state at rest and level at ``position`` with heading ``yaw``, rotors at hover speed."""
        return {
            "x": position.copy(),
            "v": np.zeros(3),
            "q": np.array([0.0, 0.0, np.sin(yaw / 2.0), np.cos(yaw / 2.0)]),  # xyzw, yaw about world z
            "w": np.zeros(3),
            "wind": np.zeros(3),  # no wind: Multirotor.step keeps it as given
            "rotor_speeds": np.full(self._params["num_rotors"], self._hover_speed),
        }

    def reset(self, position: np.ndarray, yaw: float) -> None:
        """Place the vehicle at ``position`` (3,) metres, world frame, at rest, level, heading ``yaw``
        (rad about world +z), rotors spinning at hover speed (so it neither sinks nor climbs)."""
        self._state = self._rest_state(np.asarray(position, dtype=np.float64).reshape(3), float(yaw))
        self._acceleration = np.zeros(3)

    def fly(self, flat: Callable[[float], Setpoint], t0: float, t1: float) -> VehicleTrace:
        """Fly the reference ``flat`` from time ``t0`` (the vehicle's present state) to ``t1`` seconds, in
        ``ceil((t1 - t0) * RATE_HZ)`` equal steps, each holding ``SE3Control``'s motor-speed command; the
        trace samples the step ends (``t0`` excluded, ``t1`` included; empty when ``t1 == t0``)."""
        if not (np.isfinite(t0) and np.isfinite(t1)) or t1 < t0:
            raise ValueError(f"fly needs finite times with t1 >= t0, got t0={t0!r}, t1={t1!r}")
        n = ceil((t1 - t0) * RATE_HZ - 1e-9)  # the epsilon: 1.0 s at 100 Hz is 100 steps, not 101
        times = t0 + (t1 - t0) * np.arange(1, n + 1) / max(n, 1)
        dt = (t1 - t0) / max(n, 1)
        rows = np.zeros((n, 3 + 3 + 3 + 4 + 3))
        t_prev, ref = float(t0), flat(float(t0))
        for k, t in enumerate(times.tolist()):
            # One reference evaluation per step: the sample's reference is the next step's set point.
            control = self._controller.update(t_prev, self._state, _as_rotorpy(ref, self._drag))
            self._state = self._multirotor.step(self._state, control, dt)
            if not np.all(np.isfinite(self._state["x"])):
                raise FloatingPointError(f"rotorpy's state is not finite at t={t:.3f} s: a reference it cannot fly?")
            # The acceleration at the sample from the forces (thrust, gravity, drag), not a difference.
            self._acceleration = self._multirotor.statedot(self._state, control, dt)["vdot"]
            t_prev, ref = t, flat(t)
            q = self._state["q"] if self._state["q"][3] >= 0 else -self._state["q"]  # w >= 0, as mapkit.geometry
            rows[k] = np.concatenate([self._state["x"], self._state["v"], self._acceleration, q, ref.position])
        return VehicleTrace(t=times, position=rows[:, 0:3], velocity=rows[:, 3:6], acceleration=rows[:, 6:9],
                            quaternion_xyzw=rows[:, 9:13], reference=rows[:, 13:16])

    @property
    def T_world_body(self) -> NDArray[np.float64]:
        """(4, 4) body → world transform with the vehicle's true attitude (the camera is rendered at it)."""
        return transform_from_pose(self._state["x"], self._state["q"])

    @property
    def position(self) -> NDArray[np.float64]:
        """(3,) metres, world frame."""
        return np.array(self._state["x"], dtype=np.float64)

    @property
    def velocity(self) -> NDArray[np.float64]:
        """(3,) m/s, world frame."""
        return np.array(self._state["v"], dtype=np.float64)

    @property
    def acceleration(self) -> NDArray[np.float64]:
        """(3,) m/s², world frame, from the dynamics after the last step (zero after :meth:`reset`)."""
        return np.array(self._acceleration, dtype=np.float64)

    @property
    def yaw(self) -> float:
        """Heading (rad, in (-π, π]) of the body x axis projected on the world x-y plane."""
        R = matrix_from_quat_xyzw(self._state["q"])
        return float(np.arctan2(R[1, 0], R[0, 0]))
