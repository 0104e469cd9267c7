"""`mapkit export-foxglove` and `mapkit export-rerun`."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import click

from mapkit.cli._config import ConfigSpec, Settings, config_options, field_option
from mapkit.cli._group import COUNT, POSITIVE, library_call, main, option_values, workspace_option


def _defaults() -> Any:
    from mapkit.exchange import FoxgloveConfig

    return FoxgloveConfig()


_OPTIONS = frozenset({"model", "eval_dir", "overwrite"})  # the command's options, not settings
FOXGLOVE = ConfigSpec("export-foxglove", (("", _defaults),), hidden=_OPTIONS, example="slice_heights=0.5,1.5")
RERUN = ConfigSpec("export-rerun", (("", _defaults),), hidden=_OPTIONS, example="goal_ahead=2")


@main.command("export-foxglove")
@workspace_option("Workspace to export (frames.zarr; cloud.ply and map.zarr when present).",
                  local_reason="it reads cloud.ply and writes a local file")
@click.option("-o", "--output", required=True, type=click.Path(path_type=Path), help="MCAP file to write (OUT.mcap).")
@click.option("--model", default=None, help="Run directory or \"pretrained\": add plans at --plans frames.")
@click.option("--eval", "eval_dir", type=click.Path(path_type=Path), default=None, help="A `mapkit eval` folder: add its flown paths.")
@field_option("--plans", "plan_count", spec=FOXGLOVE, key="plan_count", type=COUNT, help="Frames that get a plan (with --model).")
@field_option("--goal-ahead", spec=FOXGLOVE, key="goal_ahead", type=POSITIVE,
              help="Seconds: each plan goes to where the flight was this much later.")
@click.option("--overwrite", is_flag=True, help="Replace an existing output file.")
@config_options(FOXGLOVE)
@library_call
def export_foxglove_cmd(workspace: Path, output: Path, model: str | None, eval_dir: Path | None, plan_count: int | None,
                        goal_ahead: float | None, overwrite: bool, settings: Settings) -> None:
    """One MCAP of the flight, cloud, ESDF, plans and evaluation paths that Foxglove opens as is."""
    from mapkit.exchange import export_foxglove

    with option_values():
        config = settings.build(_defaults(), {"model": model, "eval_dir": eval_dir, "plan_count": plan_count,
                                              "goal_ahead": goal_ahead, "overwrite": overwrite})
        config.validate()
    s = export_foxglove(workspace, output, config)
    topics = ", ".join(f"{topic} {count}" for topic, count in s.messages.items())
    for note in s.notes:
        click.echo(f"note: {note}", err=True)
    click.echo(f"wrote {s.path} ({s.bytes / 1e6:.1f} MB): {topics}; ESDF as {s.esdf_as or 'none'}; {s.seconds:.1f} s")
    if model is not None:
        click.echo(_plans_line(s.messages.get("/planner/plans", 0), config.plan_count, s.plans_skipped))


@main.command("export-rerun")
@workspace_option("Workspace to export (frames.zarr; cloud.ply and map.zarr when present).",
                  local_reason="it reads cloud.ply and writes a local file")
@click.option("-o", "--output", required=True, type=click.Path(path_type=Path), help="Rerun recording to write (OUT.rrd).")
@click.option("--model", default=None, help="Run directory or \"pretrained\": add plans at --plans frames.")
@click.option("--eval", "eval_dir", type=click.Path(path_type=Path), default=None, help="A `mapkit eval` folder: add its flown paths.")
@field_option("--plans", "plan_count", spec=RERUN, key="plan_count", type=COUNT, help="Frames that get a plan (with --model).")
@field_option("--goal-ahead", spec=RERUN, key="goal_ahead", type=POSITIVE,
              help="Seconds: each plan goes to where the flight was this much later.")
@click.option("--spawn", is_flag=True, help="Open the written file in the Rerun viewer.")
@click.option("--overwrite", is_flag=True, help="Replace an existing output file.")
@config_options(RERUN)
@library_call
def export_rerun_cmd(workspace: Path, output: Path, model: str | None, eval_dir: Path | None, plan_count: int | None,
                     goal_ahead: float | None, spawn: bool, overwrite: bool, settings: Settings) -> None:
    """One .rrd of the flight, cloud, ESDF, plans and evaluation paths, with a default layout for Rerun."""
    from mapkit.exchange import export_rerun, open_in_rerun

    with option_values():
        config = settings.build(_defaults(), {"model": model, "eval_dir": eval_dir, "plan_count": plan_count,
                                              "goal_ahead": goal_ahead, "overwrite": overwrite})
        config.validate()
    s = export_rerun(workspace, output, config)
    for note in s.notes:
        click.echo(f"note: {note}", err=True)
    click.echo(f"wrote {s.path} ({s.bytes / 1e6:.1f} MB): {s.frames} frames, {s.plans} plans, {s.eval_paths} evaluation "
               f"paths; {', '.join(s.entities)}; {s.seconds:.1f} s")
    if model is not None:
        click.echo(_plans_line(s.plans, config.plan_count, s.plans_skipped))
    if spawn:
        open_in_rerun(s.path)


def _plans_line(written: int, asked: int, skipped: dict[str, int]) -> str:
    """How many of the --plans frames got a plan, and why the others did not (frames per reason)."""
    why = "; ".join(f"{frames} {reason}" for reason, frames in skipped.items())
    return f"plans: {written} of {asked} written" + (f"; skipped: {why}" if why else "")
