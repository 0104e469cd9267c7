"""What the pilot hands a vehicle's controller: a world-frame reference that can be sampled at any time
for position through snap, yaw and yaw rate."""

from __future__ import annotations

import math
import threading
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from mapkit.flight._pieces import Pieces, hold

YAW_STEP = 0.02
"""Seconds between the yaw profile's samples (yaw and yaw rate are interpolated linearly between them)."""
YAW_TAIL = 3.0
"""Seconds the yaw profile runs on past the position reference's end (a hovering vehicle turning)."""
YAW_CHUNK = 1.0
"""Seconds of yaw profile computed at a time, as far as it is sampled (references are soon replaced)."""


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


class YawFollower:
    """A yaw profile: a critically damped second-order follower of a wanted heading ``target(times)``
    (radians) whose rate stays within ``max_rate`` rad/s and acceleration within ``max_accel`` rad/s²,
    from ``yaw`` turning at ``rate`` at ``t0``, sampled every :data:`YAW_STEP` seconds until ``until``
    and computed lazily as far as it is asked for."""

    def __init__(self, target: Callable[[np.ndarray], np.ndarray], t0: float, yaw: float, rate: float,
                 max_rate: float, max_accel: float, until: float) -> None:
        self._target, self._max_rate, self._max_accel = target, max_rate, max_accel
        self._until = until
        self._omega = math.sqrt(max_accel / 0.5)  # the bandwidth at which a 0.5 rad error asks for the largest turn
        self.times, self.yaw, self.rate = np.array([t0]), np.array([float(yaw)]), np.array([float(rate)])
        self._lock = threading.Lock()  # a controller thread may sample while the pilot plans

    def _extend(self, end: float) -> None:
        t0 = float(self.times[-1])
        times = t0 + YAW_STEP * np.arange(1, max(1, int(math.ceil((end - t0) / YAW_STEP - 1e-9))) + 1)
        wanted = self._target(np.concatenate([[t0], times[:-1]]))
        yaw, rate = np.empty(len(times)), np.empty(len(times))
        y, r, w, a_max, r_max = float(self.yaw[-1]), float(self.rate[-1]), self._omega, self._max_accel, self._max_rate
        for i in range(len(times)):
            gap = (wanted[i] - y + math.pi) % (2 * math.pi) - math.pi
            accel = min(max(w * w * gap - 2.0 * w * r, -a_max), a_max)
            r_next = min(max(r + accel * YAW_STEP, -r_max), r_max)
            y += 0.5 * (r + r_next) * YAW_STEP
            r = r_next
            yaw[i], rate[i] = y, r
        self.times = np.concatenate([self.times, times])
        self.yaw, self.rate = np.concatenate([self.yaw, yaw]), np.concatenate([self.rate, rate])

    def covering(self, t: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(times, yaw, rate) computed up to ``t``, read together (another thread may extend them)."""
        with self._lock:
            while self.times[-1] < min(t, self._until) - 1e-12:
                self._extend(min(self.times[-1] + YAW_CHUNK, self._until))
            return self.times, self.yaw, self.rate


class Reference:
    """World-frame piecewise polynomials for position (:class:`Pieces`) and a yaw profile limited in rate
    and acceleration (:class:`YawFollower`). After its end it holds the end position at rest (the yaw
    profile runs :data:`YAW_TAIL` seconds longer, then holds its heading)."""

    def __init__(self, pieces: Pieces, yaw: YawFollower) -> None:
        self.pieces = pieces
        self._yaw = yaw

    @classmethod
    def holding(cls, position: np.ndarray, yaw: float, t0: float) -> Reference:
        """At rest at ``position`` (3,) facing ``yaw`` from ``t0`` on: where a vehicle waits for a goal."""
        return cls(hold(np.asarray(position, dtype=np.float64), t0), YawFollower(
            lambda t: np.full(len(t), float(yaw)), t0, yaw, 0.0, 1.0, 1.0, t0 + YAW_TAIL))

    @property
    def t_end(self) -> float:
        """Seconds: where the position reference comes to rest."""
        return self.pieces.t_end

    def derivative(self, t: np.ndarray | float, order: int) -> np.ndarray:
        """(N, 3) the ``order``-th time derivative of position (0 position … 4 snap) at times ``t`` (N,)."""
        return self.pieces.derivative(np.atleast_1d(np.asarray(t, dtype=np.float64)), order)

    def yaw(self, t: np.ndarray | float) -> np.ndarray:
        """(N,) yaw (radians, wrapped to (−π, π]) at times ``t``."""
        t = np.atleast_1d(np.asarray(t, dtype=np.float64))
        times, yaw, _ = self._yaw.covering(float(t.max()))
        wrapped: np.ndarray = np.angle(np.exp(1j * np.interp(t, times, yaw)))
        return wrapped

    def yaw_rate(self, t: np.ndarray | float) -> np.ndarray:
        """(N,) rad/s at times ``t`` (held before the profile, 0 after it)."""
        t = np.atleast_1d(np.asarray(t, dtype=np.float64))
        times, _, rate = self._yaw.covering(float(t.max()))
        return np.where(t > times[-1], 0.0, np.interp(t, times, rate))

    def sample(self, t: float) -> Setpoint:
        """The reference at time ``t`` (seconds, the pilot's clock)."""
        d = [self.derivative(t, q)[0] for q in range(5)]
        return Setpoint(t=float(t), position=d[0], velocity=d[1], acceleration=d[2], jerk=d[3], snap=d[4],
                        yaw=float(self.yaw(t)[0]), yaw_rate=float(self.yaw_rate(t)[0]))

    def state(self, t: float) -> np.ndarray:
        """(4, 3) position, velocity, acceleration, jerk at ``t`` (what the next plan starts from)."""
        return self.pieces.state(t)

    def peaks(self, t_from: float | None = None, step: float = 0.01) -> tuple[float, float]:
        """(peak speed m/s, peak acceleration m/s², norms) from ``t_from`` (its start) to its end, sampled
        every ``step`` seconds."""
        a = self.pieces.t0 if t_from is None else max(t_from, self.pieces.t0)
        t = np.linspace(a, max(a, self.t_end), int(min(5000, (max(a, self.t_end) - a) / step)) + 2)
        return (float(np.linalg.norm(self.derivative(t, 1), axis=1).max()),
                float(np.linalg.norm(self.derivative(t, 2), axis=1).max()))
