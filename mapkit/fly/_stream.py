"""The setpoint stream in a process of its own.

Why a process: in the node's process the stream thread waits for Python's interpreter lock behind the
planner and the message callbacks (a few hundred a second); measured there, one period in ten missed
its 2 ms window. Alone, the same loop keeps every period within 0.5 ms. The node sends each new
reference (its polynomials and its yaw profile, sampled ahead) through a pipe; the stream takes it as it
arrives, samples the newest one at the node's clock and publishes it.
"""

from __future__ import annotations

import multiprocessing as mp
import os
import signal
import time
from dataclasses import dataclass
from typing import Any

import numpy as np

from mapkit.flight import Pieces, Reference, Setpoint
from mapkit.fly._config import FlyConfig

STREAM_PRIORITY = 10
"""SCHED_FIFO priority the stream's loop asks for (real time, as robot control loops run; the kernel
keeps 5 % of each second for other work even so)."""
STREAM_NICE = -10
"""Niceness the stream process asks for where real time is refused."""
POLL_SLACK = 0.002
"""Seconds before a setpoint's time that waiting for references stops and a precise sleep takes over
(the pipe's wait rounds up to whole milliseconds)."""
YAW_AHEAD = 10.0
"""Seconds of the yaw profile sent with a reference beyond its end (then the heading holds)."""


@dataclass
class StreamedReference:
    """A reference as the stream process gets it: position polynomials and the yaw profile's samples,
    flown from ``start`` on (before it, the reference it replaces goes on)."""

    pieces: Pieces
    times: np.ndarray
    yaw: np.ndarray
    """Unwrapped radians at ``times``."""
    rate: np.ndarray
    start: float
    """Seconds (the node's clock) from which this reference is flown."""
    previous: StreamedReference | None = None
    """The reference flown until ``start`` (set by the stream process when this one arrives)."""

    @classmethod
    def of(cls, reference: Reference, start: float) -> StreamedReference:
        end = max(start, reference.t_end) + YAW_AHEAD
        times = np.arange(start, end, 0.02)
        return cls(reference.pieces, times, np.unwrap(reference.yaw(times)), reference.yaw_rate(times), start)

    def sample(self, t: float) -> Setpoint:
        if t < self.start and self.previous is not None:
            return self.previous.sample(t)
        d = [self.pieces.derivative(np.array([t]), q)[0] for q in range(5)]
        yaw = float(np.angle(np.exp(1j * np.interp(t, self.times, self.yaw))))
        rate = 0.0 if t > self.times[-1] else float(np.interp(t, self.times, self.rate))
        return Setpoint(t=t, position=d[0], velocity=d[1], acceleration=d[2], jerk=d[3], snap=d[4], yaw=yaw,
                        yaw_rate=rate)


class SetpointStream:
    """The stream process, seen from the node: :meth:`send` a reference, :meth:`close` to stop it."""

    def __init__(self, config: FlyConfig, sim_ns: Any, t0_ns: Any) -> None:
        ctx = mp.get_context("spawn")  # the node's process has Cyclone's and torch's threads: no fork
        self._conn, child = ctx.Pipe()
        self._process = ctx.Process(target=_run, args=(child, config, sim_ns, t0_ns), daemon=True,
                                    name="mapkit-fly-stream")
        self._process.start()
        self.times: list[float] = []
        """time.perf_counter() of each setpoint published (after :meth:`close`)."""
        self.priority = ""
        """What the stream's loop ran at: ``real time``, ``nice`` or ``default`` (after :meth:`close`)."""

    def send(self, reference: StreamedReference) -> None:
        self._conn.send(reference)

    def close(self) -> None:
        if not self._process.is_alive():
            return
        self._conn.send(None)
        if self._conn.poll(10.0):
            self.times, self.priority = self._conn.recv()
        self._process.join(5.0)
        if self._process.is_alive():
            self._process.terminate()


def _raise_priority() -> str:
    """Ahead of the planner and the sensors for the CPU, where the system allows it (root, or
    CAP_SYS_NICE): a setpoint late by more than its 2 ms is worse than a plan late by as much. Real time
    for this thread only (Cyclone's threads, made earlier, keep theirs); else a lower niceness; else
    none. Returns which."""
    try:
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(STREAM_PRIORITY))
        return "real time"
    except (PermissionError, OSError, AttributeError):  # not allowed here, or no SCHED_FIFO (not Linux)
        pass
    try:
        os.nice(STREAM_NICE)
        return "nice"
    except PermissionError:
        return "default"


def _receive_until(conn: Any, deadline: float, reference: StreamedReference | None
                   ) -> tuple[StreamedReference | None, bool]:
    """Take the references the node sends until ``deadline`` (time.perf_counter()), as they arrive, so a
    plan is flown from the next setpoint on; (the newest reference, whether the node said stop)."""
    while conn.poll(max(deadline - time.perf_counter() - POLL_SLACK, 0.0)):
        newest = conn.recv()
        if newest is None:
            return reference, True
        newest.previous, reference = reference, newest
    delay = deadline - time.perf_counter()
    if delay > 0:
        time.sleep(delay)
    return reference, False


def _run(conn: Any, config: FlyConfig, sim_ns: Any, t0_ns: Any) -> None:
    """The stream process: publish the newest reference at ``config.rate`` until told to stop."""
    from mapkit.fly import _outputs
    from mapkit.fly._dds import Link

    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C reaches the node, which stops this process
    link = Link(config.link)
    t, frames = config.topics, config.frames
    multidof = link.writer(t.setpoint, "trajectory_msgs/msg/MultiDOFJointTrajectory")
    px4 = link.writer(t.px4_setpoint, "px4_msgs/msg/TrajectorySetpoint") if config.px4 else None
    offboard = link.writer(t.px4_offboard, "px4_msgs/msg/OffboardControlMode") if config.px4 else None
    priority = _raise_priority()
    reference: StreamedReference | None = None
    times: list[float] = []
    period, deadline = 1.0 / config.rate, time.perf_counter()
    while True:
        deadline += period
        reference, stop = _receive_until(conn, deadline, reference)
        if stop:
            conn.send((times, priority))
            return
        if deadline - time.perf_counter() < -period:  # a period late (a suspended process): start the beat again
            deadline = time.perf_counter()
        if reference is None:
            continue
        now_ns = sim_ns.value if config.sim_time else time.time_ns()
        t_now = (now_ns - t0_ns.value) * 1e-9
        sp = reference.sample(t_now)
        if t_now >= reference.start:
            reference.previous = None  # flown from here on: what it replaced is done
        times.append(time.perf_counter())
        if offboard is not None and px4 is not None:
            offboard(_outputs.px4_offboard(now_ns))
            px4(_outputs.px4_setpoint(sp, now_ns))
        multidof(_outputs.multidof_setpoint(sp, now_ns, frames.world, frames.body))
