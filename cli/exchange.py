"""`mapkit export-foxglove`."""

from __future__ import annotations

from pathlib import Path

import click

from mapkit.cli.main import COUNT, POSITIVE, library_call, main, workspace_option


@main.command("export-foxglove")
@workspace_option("Workspace to export (frames.zarr; cloud.ply and map.zarr when present).")
@click.option("-o", "--output", required=True, type=click.Path(path_type=Path), help="MCAP file to write (OUT.mcap).")
@click.option("--model", default=None, help="Run directory or \"pretrained\": add plans at --plans frames.")
@click.option("--eval", "eval_dir", type=click.Path(path_type=Path), default=None, help="A `mapkit eval` folder: add its flown paths.")
@click.option("--plans", "plan_count", type=COUNT, default=12, show_default=True, help="Frames that get a plan (with --model).")
@click.option("--goal-ahead", type=POSITIVE, default=4.0, show_default=True,
              help="Seconds: each plan goes to where the flight was this much later.")
@click.option("--overwrite", is_flag=True, help="Replace an existing output file.")
@library_call
def export_foxglove_cmd(workspace: Path, output: Path, model: str | None, eval_dir: Path | None, plan_count: int,
                        goal_ahead: float, overwrite: bool) -> None:
    """One MCAP of the flight, cloud, ESDF, plans and evaluation paths that Foxglove opens as is."""
    from mapkit.exchange import FoxgloveConfig, export_foxglove

    config = FoxgloveConfig(model=model, eval_dir=eval_dir, plan_count=plan_count, goal_ahead=goal_ahead, overwrite=overwrite)
    s = export_foxglove(workspace, output, config)
    topics = ", ".join(f"{topic} {count}" for topic, count in s.messages.items())
    click.echo(f"wrote {s.path}: {topics}; ESDF as {s.esdf_as or 'none (no map.zarr)'}; {s.seconds:.1f} s")
