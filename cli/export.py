"""`mapkit export`."""

from __future__ import annotations

from pathlib import Path

import click

from mapkit.cli._group import COUNT, INDEX, NONNEGATIVE, POSITIVE, library_call, main, option_values, workspace_option


@main.command("export")
@workspace_option("Workspace with frames.zarr and map.zarr.", urls=True)
@click.option("--goals-per-frame", type=COUNT, default=5, show_default=True, help="Goals per frame, split by --goal-mix.")
@click.option("--goal-mix", type=NONNEGATIVE, nargs=3, default=(0.2, 0.4, 0.4), show_default=True,
              help="Shares of FUTURE (poses the flight reached) VISIBLE (free space in view) HIDDEN (straight line blocked in the map) goals.")
@click.option("--goal-range", type=POSITIVE, nargs=2, default=(2.0, 8.0), show_default=True, help="MIN MAX metres of visible and hidden goals.")
@click.option("--hidden-bearing", type=POSITIVE, default=75.0, show_default=True, help="Degrees off the heading within which hidden goals lie.")
@click.option("--future-horizon", type=NONNEGATIVE, nargs=2, default=(1.0, 5.0), show_default=True, help="MIN MAX seconds ahead for future-pose goals.")
@click.option("--clearance", type=NONNEGATIVE, default=0.3, show_default=True, help="Metres every goal keeps from obstacles.")
@click.option("--val-fraction", type=NONNEGATIVE, default=0.2, show_default=True, help="Share of contiguous segments for validation.")
@click.option("--segment-seconds", type=POSITIVE, default=2.0, show_default=True, help="Length of the segments the split assigns whole.")
@click.option("--seed", type=INDEX, default=0, show_default=True, help="Seed of goal sampling and split.")
@click.option("--stride", type=COUNT, default=1, show_default=True, help="Export every N-th frame.")
@click.option("--overwrite", is_flag=True, help="Replace an existing tuples.zarr.")
@library_call
def export_cmd(workspace: Path, goals_per_frame: int, goal_mix: tuple[float, float, float], goal_range: tuple[float, float],
               hidden_bearing: float, future_horizon: tuple[float, float],
               clearance: float, val_fraction: float, segment_seconds: float, seed: int, stride: int, overwrite: bool) -> None:
    """Training tuples (depth, poses, velocity, goals in the body frame, split) → WS/tuples.zarr."""
    from mapkit.export import ExportConfig, export_tuples

    with option_values():
        config = ExportConfig(goals_per_frame=goals_per_frame, goal_mix=goal_mix, goal_range=goal_range,
                              hidden_bearing_deg=hidden_bearing, future_horizon=future_horizon,
                              clearance=clearance, val_fraction=val_fraction, segment_seconds=segment_seconds,
                              seed=seed, stride=stride)
        config.validate()
    s = export_tuples(workspace, config, overwrite=overwrite, progress=True)
    click.echo(
        f"wrote {s.path}: {s.frames} tuples ({s.train} train, {s.val} val), {s.goals} goals "
        f"({s.future_goals} future poses); {s.dropped_frames} frames without enough valid goals; {s.seconds:.1f} s\n"
        f"  {s.mix_text()}"
    )
