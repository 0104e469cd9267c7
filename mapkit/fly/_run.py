"""`mapkit fly` as one call: load the pilot, open the link (and the recording), run the node until
Ctrl-C or a duration, and say what it did."""

from __future__ import annotations

import logging
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from mapkit.fly._config import FlyConfig
from mapkit.fly._dds import Link
from mapkit.fly._node import FlyNode, log
from mapkit.fly._record import Recording

STATUS_EVERY = 5.0
"""Seconds between two status lines on the terminal."""


@dataclass
class FlySummary:
    """What a `mapkit fly` session did."""

    seconds: float
    setpoints: int
    plans: int
    frames_dropped: int
    late_plans: int
    """Plans that reached the setpoint stream after their takeover time (see FlyNode.late_plans)."""
    last_state: str
    last_reason: str
    problems: dict[str, int]
    recording: Path | None
    recorded_messages: int

    def text(self) -> str:
        problems = ", ".join(f"{k}: {n}" for k, n in sorted(self.problems.items())) or "none"
        out = (f"flew {self.seconds:.0f} s: {self.setpoints} setpoints, {self.plans} frames planned from, "
               f"{self.frames_dropped} frames skipped while planning, {self.late_plans} plans late for their "
               f"takeover; last state {self.last_state} "
               f"({self.last_reason}); problems: {problems}")
        if self.recording is not None:
            out += f"\nwrote {self.recording} ({self.recorded_messages} messages)"
        return out


def fly(model: str | Path, config: FlyConfig, *, goal: np.ndarray | None = None, duration: float | None = None,
        status_lines: bool = True) -> FlySummary:
    """Fly `model` (a run directory or "pretrained") on the ROS 2 graph until Ctrl-C or `duration`
    seconds; `goal` (world frame) is taken as if it arrived on the goal topic."""
    from mapkit.flight import Pilot

    config.validate()
    # The stream thread must get the interpreter within a fraction of its 2 ms budget while the planner
    # runs Python: a thread waits up to this long for the lock (5 ms by default).
    sys.setswitchinterval(0.0005)
    pilot = Pilot.load(model, config=config.pilot)
    recording = None if config.record is None else Recording(config.record)
    link = Link(config.link, tap=None if recording is None else recording.write)
    node = FlyNode(pilot, config, link)
    started = time.monotonic()
    try:
        node.start()
        if recording is not None:  # the stream process publishes the setpoints: record them as they arrive
            _listen_to_setpoints(link, config)
        log.info("flying %s on domain %d over %s%s", model, config.link.domain_id, config.link.interface,
                 " (dry run: no setpoints)" if config.dry_run else "")
        if goal is not None:
            _goal_when_seen(node, goal, duration)
        _wait(node, started, duration, status_lines)
    finally:
        node.close()  # the setpoint stream stops first
        if recording is not None:
            recording.close()
        # The participant is left to the process's exit (the link's atexit hook deletes it): the
        # caller may still be reading on it, and the node is stopped, so nothing more is sent.
    st = node.status
    return FlySummary(time.monotonic() - started, len(node.setpoint_times), len(node.steps), node.frames_dropped,
                      node.late_plans, st["state"], st["reason"], st["problems"], config.record,
                      0 if recording is None else recording.messages)


def _listen_to_setpoints(link: Link, config: FlyConfig) -> None:
    t = config.topics
    topics = [(t.setpoint, "trajectory_msgs/msg/MultiDOFJointTrajectory")]
    if config.px4:
        topics += [(t.px4_setpoint, "px4_msgs/msg/TrajectorySetpoint"),
                   (t.px4_offboard, "px4_msgs/msg/OffboardControlMode")]
    for topic, msgtype in topics:
        link.reader(topic, msgtype, lambda msg, received_ns: None, qos="reliable")


def _goal_when_seen(node: FlyNode, goal: np.ndarray, duration: float | None) -> None:
    """Set `goal` once odometry has arrived (the geofence is centred on it)."""
    end = None if duration is None else time.monotonic() + duration
    while node.status["odometry_age"] is None:
        if end is not None and time.monotonic() > end:
            return
        time.sleep(0.05)
    node.set_goal(np.asarray(goal, dtype=np.float64))


def _wait(node: FlyNode, started: float, duration: float | None, status_lines: bool) -> None:
    last = 0.0
    while duration is None or time.monotonic() - started < duration:
        time.sleep(0.1)
        if status_lines and time.monotonic() - last >= STATUS_EVERY:
            last = time.monotonic()
            st = node.status
            log.info("%s: %s (odometry age %s s, depth age %s s)", st["state"], st["reason"], st["odometry_age"],
                     st["depth_age"])


def log_to_stderr(level: int = logging.INFO) -> None:
    """One line per record on stderr, for the CLI."""
    handler = logging.StreamHandler(sys.stderr)
    handler.setFormatter(logging.Formatter("%(asctime)s %(levelname)s %(message)s", "%H:%M:%S"))
    log.addHandler(handler)
    log.setLevel(level)
    log.propagate = False  # one line per record, whatever the root logger does
