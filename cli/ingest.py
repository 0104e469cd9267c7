"""`mapkit info` and `mapkit ingest`."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any

import click

from mapkit.cli._group import COUNT, POSITIVE, library_call, main, option_values, workspace_option
from mapkit.ingest import IngestConfig, IngestError, ingest, inspect_recordings
from mapkit.ingest._decode import parse_extrinsic, parse_intrinsics

RECORDINGS = click.argument("recordings", nargs=-1, required=True, type=click.Path(path_type=Path))


def ingest_options(func: Callable[..., Any]) -> Callable[..., Any]:
    """The role overrides and sync options shared by every command that reads recordings."""
    options = [
        click.option("--depth-topic", help="Depth image topic (default: auto-detect by type and encoding)."),
        click.option("--camera-info-topic", help="CameraInfo topic (default: auto-detect)."),
        click.option("--pose-topic", help="Odometry/PoseStamped topic, or 'tf' to use the tf tree only."),
        click.option("--world-frame", help="Fixed frame of output poses (default: the pose topic's frame or tf root)."),
        click.option("--camera-frame", help="Optical frame of the depth camera (default: the images' frame_id)."),
        click.option("--body-frame", help="Body frame (default: Odometry child frame / start of the static chain)."),
        click.option("--intrinsics", metavar="FX,FY,CX,CY", help="Camera intrinsics when the recording has no CameraInfo."),
        click.option("--extrinsic", metavar="X,Y,Z,QX,QY,QZ,QW", help="T_body_camera (optical), overriding tf_static; or 'identity'."),
        click.option("--max-pose-gap", type=POSITIVE, default=0.1, show_default=True, help="Seconds; drop frames inside longer pose gaps."),
        click.option("--stride", type=COUNT, default=1, show_default=True, help="Keep every N-th depth message."),
        click.option("--max-frames", type=COUNT, default=None, help="Stop after this many frames."),
        click.option("--drop-nonmonotonic", is_flag=True, help="Drop messages whose stamp goes backwards instead of failing."),
    ]
    for option in reversed(options):
        func = option(func)
    return func


def build_config(**kw: Any) -> IngestConfig:
    """The ingest options as a checked config; a malformed or out-of-range value is a usage error."""
    with option_values():
        config = _ingest_config(**kw)
        config.validate()
    return config


def _ingest_config(**kw: Any) -> IngestConfig:
    return IngestConfig(
        depth_topic=kw["depth_topic"],
        camera_info_topic=kw["camera_info_topic"],
        pose_topic=kw["pose_topic"],
        world_frame=kw["world_frame"],
        camera_frame=kw["camera_frame"],
        body_frame=kw["body_frame"],
        intrinsics=parse_intrinsics(kw["intrinsics"]) if kw["intrinsics"] else None,
        extrinsic=parse_extrinsic(kw["extrinsic"]) if kw["extrinsic"] else None,
        max_pose_gap=kw["max_pose_gap"],
        stride=kw["stride"],
        max_frames=kw["max_frames"],
        drop_nonmonotonic=kw["drop_nonmonotonic"],
    )


@main.command()
@RECORDINGS
@ingest_options
@library_call
def info(recordings: tuple[Path, ...], **kw: Any) -> None:
    """Topics, types, counts, rates and time span of RECORDINGS, and the topics ingestion would use.

    Exits 1 when a recording lacks a depth, camera-info or pose source.
    """
    config = build_config(**kw)
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
@ingest_options
@library_call
def ingest_cmd(recordings: tuple[Path, ...], workspace: Path, overwrite: bool, **kw: Any) -> None:
    """Decode and synchronise RECORDINGS into WORKSPACE/frames.zarr."""
    summary = ingest(list(recordings), workspace, build_config(**kw), overwrite=overwrite, progress=True)
    for w in summary.warnings:
        click.echo(f"warning: {w}", err=True)
    dropped = ", ".join(f"{k} {v}" for k, v in summary.dropped.items()) or "none"
    click.echo(
        f"wrote {summary.path}: {summary.frames} frames {summary.width}x{summary.height} from "
        f"{summary.depth_messages} depth messages in {len(summary.sources)} recording(s); dropped: {dropped}; "
        f"{summary.seconds:.1f} s ({summary.frames_per_second:.0f} frames/s)"
    )
