"""`mapkit replay`: a ROS 2 recording (MCAP, rosbag2) played back as live topics, at its own pace.

The recorded CDR goes onto the wire as it is. With ``clock``, /clock follows the recording's log times,
so a node on simulator time (``mapkit fly --sim-time``) sees the flight as it was recorded."""

from __future__ import annotations

import time
from collections.abc import Iterable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from mapkit.fly._dds import Link
from mapkit.fly._errors import FlyError
from mapkit.fly._msgs import message, typestore
from mapkit.ingest import Source


@dataclass
class ReplaySummary:
    """What a replay published."""

    messages: int = 0
    seconds: float = 0.0
    topics: dict[str, int] = field(default_factory=dict)
    skipped: dict[str, str] = field(default_factory=dict)
    """Topics not played, and why (a message type this mapkit does not know)."""


def _qos(topic: str) -> str:
    return "latched" if topic.endswith("tf_static") else "reliable"


def replay(path: str | Path, link: Link, *, topics: Iterable[str] | None = None, rate: float = 1.0,
           clock: bool = False) -> ReplaySummary:
    """Publish the recording at `path` on `link`: every topic (or `topics`), at `rate` × its pace."""
    if not rate > 0:
        raise FlyError(f"replay rate {rate} must be > 0 (1 is the recorded pace)")
    out = ReplaySummary()
    with Source(path) as source:
        if source.kind == "ros1":
            raise FlyError(f"{path} is a ROS 1 bag; replay plays ROS 2 recordings (MCAP, rosbag2): convert it "
                           "with `rosbags-convert`")
        known = typestore().fielddefs
        wanted = list(source.summary.topics) if topics is None else list(topics)
        writers: dict[str, Any] = {}
        for name in wanted:
            info = source.summary.topics.get(name)
            if info is None:
                raise FlyError(f"{path} has no topic {name}; it has {', '.join(sorted(source.summary.topics))}")
            if info.msgtype not in known:
                out.skipped[name] = f"message type {info.msgtype} is unknown here"
                continue
            writers[name] = link.raw_writer(name, info.msgtype, qos=_qos(name))
        publish_clock = link.writer("/clock", "rosgraph_msgs/msg/Clock") if clock else None
        _play(source, writers, rate, publish_clock, out)
    return out


def _play(source: Source, writers: dict[str, Any], rate: float, publish_clock: Any, out: ReplaySummary) -> None:
    first: int | None = None
    wall0 = time.monotonic()
    for raw in source.messages(writers):
        first = raw.log_time_ns if first is None else first
        due = (raw.log_time_ns - first) * 1e-9 / rate - (time.monotonic() - wall0)
        if due > 0:
            time.sleep(due)
        if publish_clock is not None:
            stamp = message("builtin_interfaces/msg/Time", sec=raw.log_time_ns // 1_000_000_000,
                            nanosec=raw.log_time_ns % 1_000_000_000)
            publish_clock(message("rosgraph_msgs/msg/Clock", clock=stamp))
        writers[raw.topic](bytes(raw.data))
        out.messages += 1
        out.topics[raw.topic] = out.topics.get(raw.topic, 0) + 1
    out.seconds = time.monotonic() - wall0
