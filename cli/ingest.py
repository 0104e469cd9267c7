"""`mapkit info` and `mapkit ingest`."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any

import click
import numpy as np

from mapkit.cli._config import Codec, ConfigSpec, Settings, config_options, field_option
from mapkit.cli._group import library_call, main, option_values, workspace_option
from mapkit.ingest import IngestConfig, IngestError, ingest, inspect_recordings
from mapkit.ingest._decode import parse_extrinsic, parse_intrinsics

RECORDINGS = click.argument("recordings", nargs=-1, required=True, type=click.Path(path_type=Path))


def _text(value: Any, what: str) -> str:
    """A TOML value of numbers as the comma text the parsers read (a list of numbers, or the text itself)."""
    if isinstance(value, str):
        return value
    if isinstance(value, (list, tuple)) and all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in value):
        return ",".join(str(v) for v in value)
    raise ValueError(f"expected {what}")


def _read_extrinsic(value: Any) -> Any:
    if isinstance(value, list) and len(value) == 4:  # the 4x4 matrix, as `mapkit config` shows one
        return np.asarray(value, dtype=np.float64)
    return parse_extrinsic(_text(value, '"identity", "X,Y,Z,QX,QY,QZ,QW" or a list of those 7 numbers'))


INGEST_TABLE = ("ingest", IngestConfig)
"""Every command that reads recordings has the ingest settings as the table ``ingest``: one file
serves info, ingest, fuse and batch alike."""
INGEST_CODECS = {
    "ingest.intrinsics": Codec(
        read=lambda v: parse_intrinsics(_text(v, '"FX,FY,CX,CY" or a list of those 4 numbers')),
        show=lambda K: [K[0, 0], K[1, 1], K[0, 2], K[1, 2]]),
    "ingest.extrinsic": Codec(read=_read_extrinsic, show=lambda T: np.asarray(T).tolist()),
}
"""The camera's matrices: written as the numbers that make them."""


def ingest_options(spec: ConfigSpec) -> Callable[[Callable[..., Any]], Callable[..., Any]]:
    """The role overrides a recording without the usual topics needs every time (the other ingest
    settings are ``--set ingest.NAME=VALUE``): --depth-topic, --pose-topic, --intrinsics."""
    options = [
        field_option("--depth-topic", spec=spec, key="ingest.depth_topic",
                     help="Depth image topic (default: auto-detect by type and encoding)."),
        field_option("--pose-topic", spec=spec, key="ingest.pose_topic",
                     help="Odometry/PoseStamped topic, or 'tf' to use the tf tree only (default: auto-detect)."),
        field_option("--intrinsics", spec=spec, key="ingest.intrinsics", metavar="FX,FY,CX,CY",
                     help="Camera intrinsics when the recording has no CameraInfo."),
    ]

    def decorate(func: Callable[..., Any]) -> Callable[..., Any]:
        for option in reversed(options):
            func = option(func)
        return func

    return decorate


def build_config(settings: Settings, depth_topic: str | None, pose_topic: str | None,
                 intrinsics: str | None) -> IngestConfig:
    """The ingest settings and options as a checked config; a malformed or out-of-range value is a usage error."""
    with option_values():
        given = {"ingest.depth_topic": depth_topic, "ingest.pose_topic": pose_topic,
                 "ingest.intrinsics": parse_intrinsics(intrinsics) if intrinsics else None}
        config = settings.build(IngestConfig(), given, table="ingest")
        config.validate()
    return config


INFO = ConfigSpec("info", (INGEST_TABLE,), codecs=INGEST_CODECS, example="ingest.extrinsic=identity")
INGEST = ConfigSpec("ingest", (INGEST_TABLE,), codecs=INGEST_CODECS, example="ingest.stride=2")


@main.command()
@RECORDINGS
@ingest_options(INFO)
@config_options(INFO)
@library_call
def info(recordings: tuple[Path, ...], settings: Settings, **kw: Any) -> None:
    """Topics, types, counts, rates and time span of RECORDINGS, and the topics ingestion would use.

    Exits 1 when a recording lacks a depth, camera-info or pose source.
    """
    config = build_config(settings, **kw)
    problems = []
    for item in inspect_recordings(list(recordings), config):
        s = item.summary
        click.echo(f"{s.path}  [{s.format_name}]")
        click.echo(f"  span {s.start_ns / 1e9:.3f} – {s.end_ns / 1e9:.3f} s ({s.duration_s:.2f} s)")
        width = max((len(t) for t in s.topics), default=5)
        click.echo(f"  {'topic':<{width}}  {'type':<44} {'count':>7} {'rate Hz':>8}")
        for t in sorted(s.topics.values(), key=lambda t: t.name):
            rate = (t.count - 1) / s.duration_s if s.duration_s > 0 and t.count > 1 else 0.0
            click.echo(f"  {t.name:<{width}}  {t.msgtype:<44} {t.count:>7} {rate:>8.1f}")
        for w in s.warnings:
            click.echo(f"  warning: {w}")
        if item.plan is not None:
            p = item.plan
            click.echo("  would use:")
            click.echo(f"    depth        {p.depth.topic} ({p.depth_encoding}): {p.depth.why}")
            click.echo(f"    camera info  {p.camera_info.topic or '--intrinsics'}: {p.camera_info.why}")
            click.echo(f"    pose         {p.pose.topic or 'tf'}: {p.pose.why}")
            fx, fy, cx, cy = p.K[0, 0], p.K[1, 1], p.K[0, 2], p.K[1, 2]
            click.echo(f"    intrinsics   fx={fx:.2f} fy={fy:.2f} cx={cx:.2f} cy={cy:.2f}")
            click.echo(f"    frames       world={p.world_frame} body={p.body_frame} camera={p.camera_frame}")
        else:
            problems.append(f"{s.path}: {item.problem}")
    if problems:
        raise IngestError("; ".join(problems))


@main.command("ingest")
@RECORDINGS
@workspace_option("Workspace directory.", urls=True)
@click.option("--overwrite", is_flag=True, help="Replace an existing frames.zarr.")
@ingest_options(INGEST)
@config_options(INGEST)
@library_call
def ingest_cmd(recordings: tuple[Path, ...], workspace: Path, overwrite: bool, settings: Settings, **kw: Any) -> None:
    """Decode and synchronise RECORDINGS into WORKSPACE/frames.zarr (every setting: `mapkit config ingest`)."""
    summary = ingest(list(recordings), workspace, build_config(settings, **kw), overwrite=overwrite, progress=True)
    for w in summary.warnings:
        click.echo(f"warning: {w}", err=True)
    dropped = ", ".join(f"{k} {v}" for k, v in summary.dropped.items()) or "none"
    click.echo(
        f"wrote {summary.path}: {summary.frames} frames {summary.width}x{summary.height} from "
        f"{summary.depth_messages} depth messages in {len(summary.sources)} recording(s); dropped: {dropped}; "
        f"{summary.seconds:.1f} s ({summary.frames_per_second:.0f} frames/s)"
    )
