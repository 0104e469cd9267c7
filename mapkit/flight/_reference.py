"""What the pilot hands a vehicle's controller: a world-frame reference that can be sampled at any time
for position through snap, yaw and yaw rate."""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from mapkit.flight._pieces import Pieces

YAW_STEP = 0.02
"""Seconds between the yaw profile's samples (yaw and yaw rate are interpolated linearly between them)."""
YAW_TAIL = 3.0
"""Seconds the yaw profile runs on past the position reference's end (a hovering vehicle turning)."""


@dataclass(frozen=True)
class Setpoint:
    """The reference at one time, world frame (ENU, z up), SI units: what a position / velocity /
    acceleration controller (or a flatness-based one, e.g. SE(3) geometric control) tracks."""

    t: float
    """Seconds, the pilot's clock (the stamps it is given)."""
    position: np.ndarray
    """(3,) metres."""
    velocity: np.ndarray
    """(3,) m/s."""
    acceleration: np.ndarray
    """(3,) m/s² (gravity not included)."""
    jerk: np.ndarray
    """(3,) m/s³."""
    snap: np.ndarray
    """(3,) m/s⁴."""
    yaw: float
    """Radians from +x (east) counter-clockwise, in (−π, π]: the heading of the body's x axis."""
    yaw_rate: float
    """rad/s."""


class Reference:
    """World-frame piecewise polynomials for position (:class:`Pieces`, degree 7 for minimum-snap
    plans) and a yaw profile limited in rate and acceleration. Before its start it holds the start; after its end it holds
    the end position at rest (the yaw profile runs :data:`YAW_TAIL` seconds longer, then holds)."""

    def __init__(self, pieces: Pieces, yaw_times: np.ndarray, yaw: np.ndarray, yaw_rate: np.ndarray) -> None:
        self.pieces = pieces
        self._yaw_t = np.asarray(yaw_times, dtype=np.float64).reshape(-1)
        self._yaw = np.asarray(yaw, dtype=np.float64).reshape(-1)  # unwrapped
        self._rate = np.asarray(yaw_rate, dtype=np.float64).reshape(-1)
        n = len(self._yaw_t)
        if n < 2 or len(self._yaw) != n or len(self._rate) != n or np.any(np.diff(self._yaw_t) <= 0):
            raise ValueError("the yaw profile needs two or more samples (times, yaw, yaw rate) at increasing times")

    @property
    def t_start(self) -> float:
        """Seconds: where the reference begins (the switch from the previous one)."""
        return self.pieces.t0

    @property
    def t_end(self) -> float:
        """Seconds: where the position reference comes to rest."""
        return self.pieces.t_end

    def derivative(self, t: np.ndarray | float, order: int) -> np.ndarray:
        """(N, 3) the ``order``-th time derivative of position (0 position … 4 snap) at times ``t`` (N,)."""
        return self.pieces.derivative(np.atleast_1d(np.asarray(t, dtype=np.float64)), order)

    def yaw(self, t: np.ndarray | float) -> np.ndarray:
        """(N,) yaw (radians, wrapped to (−π, π]) at times ``t``."""
        y = np.interp(np.atleast_1d(np.asarray(t, dtype=np.float64)), self._yaw_t, self._yaw)
        wrapped: np.ndarray = np.angle(np.exp(1j * y))
        return wrapped

    def yaw_rate(self, t: np.ndarray | float) -> np.ndarray:
        """(N,) rad/s at times ``t`` (held before the profile, 0 after it)."""
        t = np.atleast_1d(np.asarray(t, dtype=np.float64))
        return np.where(t > self._yaw_t[-1], 0.0, np.interp(t, self._yaw_t, self._rate))

    def sample(self, t: float) -> Setpoint:
        """The reference at time ``t`` (seconds, the pilot's clock)."""
        d = [self.derivative(t, q)[0] for q in range(5)]
        return Setpoint(t=float(t), position=d[0], velocity=d[1], acceleration=d[2], jerk=d[3], snap=d[4],
                        yaw=float(self.yaw(t)[0]), yaw_rate=float(self.yaw_rate(t)[0]))

    def state(self, t: float) -> np.ndarray:
        """(4, 3) position, velocity, acceleration, jerk at ``t`` (what the next plan starts from)."""
        return self.pieces.state(t)

    def peaks(self, t_from: float | None = None, step: float = 0.01) -> tuple[float, float]:
        """(peak speed m/s, peak acceleration m/s²) from ``t_from`` (its start) to its end, sampled every
        ``step`` seconds: the largest magnitude on any world axis, the measure of the speed profile's
        per-axis limits (:class:`~mapkit.flight.SpeedProfile`)."""
        a = self.t_start if t_from is None else max(t_from, self.t_start)
        t = np.arange(a, max(a, self.t_end) + step, step)
        return float(np.abs(self.derivative(t, 1)).max()), float(np.abs(self.derivative(t, 2)).max())


def yaw_profile(pieces: Pieces, t_from: float, yaw_from: float, rate_from: float,
                target: Callable[[np.ndarray], np.ndarray], max_rate: float, max_accel: float
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(times (N,), unwrapped yaw (N,), yaw rate (N,)): from ``yaw_from`` turning at ``rate_from`` at
    ``t_from`` toward ``target(times)`` (radians), every :data:`YAW_STEP` seconds until :data:`YAW_TAIL`
    seconds past the end of ``pieces``: a critically damped second-order follower whose rate stays
    within ``max_rate`` rad/s and whose acceleration within ``max_accel`` rad/s². Written by hand: a
    step in the wanted heading (a hovering vehicle turning to look elsewhere) must become a turn a
    quadrotor can follow (its yaw torque is small), and the profile starts where the last one was at
    the switch, so yaw and yaw rate are continuous from plan to plan."""
    end = max(t_from, pieces.t_end) + YAW_TAIL
    times = t_from + YAW_STEP * np.arange(int(math.ceil((end - t_from) / YAW_STEP)) + 1)
    wanted = target(times)
    yaw, rate = np.empty(len(times)), np.empty(len(times))
    yaw[0], rate[0] = yaw_from, rate_from
    omega = math.sqrt(max_accel / 0.5)  # the bandwidth at which a 0.5 rad error asks for the largest turn
    for i in range(1, len(times)):
        gap = (wanted[i - 1] - yaw[i - 1] + math.pi) % (2 * math.pi) - math.pi
        accel = min(max(omega * omega * gap - 2.0 * omega * rate[i - 1], -max_accel), max_accel)
        rate[i] = min(max(rate[i - 1] + accel * YAW_STEP, -max_rate), max_rate)
        yaw[i] = yaw[i - 1] + 0.5 * (rate[i - 1] + rate[i]) * YAW_STEP
    return times, yaw, rate
