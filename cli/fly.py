"""`mapkit fly` and `mapkit replay`: the pilot on a live ROS 2 / PX4 graph over DDS, and recordings
played back as live topics."""

from __future__ import annotations

import os
import signal
import sys
from pathlib import Path
from typing import Any

import click

from mapkit.cli._config import ConfigSpec, Settings, config_options, field_option
from mapkit.cli._group import FINITE, POSITIVE, library_call, main, option_values


def _defaults() -> Any:
    from mapkit.fly import FlyConfig

    return FlyConfig()


FLY = ConfigSpec("fly", (("", _defaults),), example="topics.depth=/d435/depth/image_rect_raw")


def _domain_id(value: int | None) -> int | None:
    """--domain-id, else ROS_DOMAIN_ID as ROS 2 reads it, else the config's."""
    if value is not None:
        return value
    env = os.environ.get("ROS_DOMAIN_ID", "").strip()
    if not env:
        return None
    if not env.isdigit():
        raise click.UsageError(f"ROS_DOMAIN_ID={env!r} is not a domain id; set it to 0-232 or unset it")
    return int(env)


@main.command("fly")
@click.option("--model", default="pretrained", show_default=True, help="Run directory, or \"pretrained\".")
@click.option("--goal", type=FINITE, nargs=3, default=None, metavar="X Y Z",
              help="A first goal, world frame (more arrive on topics.goal).")
@field_option("--odometry", "odometry_type", spec=FLY, key="topics.odometry_type",
              type=click.Choice(["nav_msgs", "px4"]), help="Odometry message: nav_msgs/Odometry or PX4's VehicleOdometry.")
@field_option("--interface", spec=FLY, key="link.interface", metavar="NAME",
              help="Network interface (lo: this machine only; e.g. eth0 to reach the vehicle's computer).")
@click.option("--domain-id", type=click.IntRange(0, 232), default=None, help="ROS domain id (default: ROS_DOMAIN_ID, else 0).")
@field_option("--enclave", spec=FLY, key="link.enclave", metavar="DIR",
              help="ROS 2 security enclave (`ros2 security create_enclave`): DDS Security on (docs/fly.md).")
@field_option("--rate", spec=FLY, key="rate", type=POSITIVE, metavar="HZ")
@field_option("--dry-run", spec=FLY, key="dry_run", is_flag=True, default=None)
@field_option("--sim-time", spec=FLY, key="sim_time", is_flag=True, default=None)
@field_option("--record", spec=FLY, key="record", type=click.Path(path_type=Path), metavar="OUT.mcap")
@click.option("--duration", type=POSITIVE, default=None, metavar="S", help="Stop after S seconds (default: Ctrl-C).")
@config_options(FLY)
@library_call
def fly_cmd(model: str, goal: tuple[float, float, float] | None, odometry_type: str | None, interface: str | None,
            domain_id: int | None, enclave: str | None, rate: float | None, dry_run: bool | None, sim_time: bool | None,
            record: Path | None, duration: float | None, settings: Settings) -> None:
    """Fly the planner on a robot's ROS 2 graph (PX4 over uXRCE-DDS, or any ROS 2 autopilot), no ROS needed.

    Reads depth, camera info, odometry, tf and goals; publishes setpoints (PX4 TrajectorySetpoint and
    OffboardControlMode in NED; MultiDOFJointTrajectory), the plan as nav_msgs/Path and the status.
    Loopback only unless --interface names a network. Ctrl-C stops the setpoint stream (PX4 then falls
    back to its failsafe). Wiring, frames and safety: docs/fly.md; every setting: `mapkit config fly`.
    """
    import numpy as np

    from mapkit.fly import fly
    from mapkit.fly._run import log_to_stderr

    with option_values():
        config = settings.build(_defaults(), {
            "topics.odometry_type": odometry_type, "link.interface": interface, "link.domain_id": _domain_id(domain_id),
            "link.enclave": enclave, "rate": rate, "dry_run": dry_run, "sim_time": sim_time, "record": record})
        config.validate()
    log_to_stderr()
    signal.signal(signal.SIGTERM, signal.default_int_handler)  # launch files and systemd stop with SIGTERM
    try:
        summary = fly(model, config, goal=None if goal is None else np.array(goal), duration=duration)
    except KeyboardInterrupt:  # fly() has stopped the stream and closed the recording on its way out
        click.echo("interrupted: setpoint stream stopped", err=True)
        _exit(130)
    click.echo(summary.text())
    _exit(0)


def _exit(code: int) -> None:
    """Leave without the interpreter's teardown: Cyclone's threads may still call into Python, and
    tearing down under them can hang (everything the node owns is stopped and written by now)."""
    sys.stdout.flush()
    sys.stderr.flush()
    os._exit(code)


@main.command("replay")
@click.argument("recording", type=click.Path(path_type=Path, exists=True))
@click.option("--topic", "topics", multiple=True, help="Play only this topic (repeatable; default: all).")
@click.option("--rate", type=POSITIVE, default=1.0, show_default=True, help="Playback speed, × the recorded pace.")
@click.option("--clock", is_flag=True, help="Publish /clock from the recording's times (for --sim-time nodes).")
@click.option("--interface", default="lo", show_default=True, help="Network interface (lo: this machine only).")
@click.option("--domain-id", type=click.IntRange(0, 232), default=None, help="ROS domain id (default: ROS_DOMAIN_ID, else 0).")
@library_call
def replay_cmd(recording: Path, topics: tuple[str, ...], rate: float, clock: bool, interface: str,
               domain_id: int | None) -> None:
    """Play a ROS 2 recording (MCAP, rosbag2) back as live DDS topics, at its recorded pace."""
    from mapkit.fly import DdsConfig, Link
    from mapkit.fly._replay import replay

    with option_values():
        link_config = DdsConfig(domain_id=_domain_id(domain_id) or 0, interface=interface)
    link = Link(link_config)
    try:
        out = replay(recording, link, topics=topics or None, rate=rate, clock=clock)
    finally:
        link.close()
    played = ", ".join(f"{t} {n}" for t, n in sorted(out.topics.items())) or "nothing"
    click.echo(f"played {out.messages} messages in {out.seconds:.1f} s: {played}")
    for topic, why in sorted(out.skipped.items()):
        click.echo(f"  skipped {topic}: {why}")
