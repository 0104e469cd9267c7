"""`mapkit export`."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import click

from mapkit.cli._config import ConfigSpec, Settings, config_options, field_option
from mapkit.cli._group import INDEX, library_call, main, option_values, workspace_option


def _defaults() -> Any:
    from mapkit.export import ExportConfig

    return ExportConfig()


EXPORT = ConfigSpec("export", (("", _defaults),), example="goal_mix=0.2,0.4,0.4")


@main.command("export")
@workspace_option("Workspace with frames.zarr and map.zarr.", urls=True)
@field_option("--seed", spec=EXPORT, key="seed", type=INDEX)
@click.option("--overwrite", is_flag=True, help="Replace an existing tuples.zarr.")
@config_options(EXPORT)
@library_call
def export_cmd(workspace: Path, seed: int | None, overwrite: bool, settings: Settings) -> None:
    """Training tuples (depth, poses, velocity, goals in the body frame, split) → WS/tuples.zarr.

    Goals per frame, their mix (future poses, visible, hidden), ranges, clearance and the split are
    settings: `mapkit config export`.
    """
    from mapkit.export import export_tuples

    with option_values():
        config = settings.build(_defaults(), {"seed": seed})
        config.validate()
    s = export_tuples(workspace, config, overwrite=overwrite, progress=True)
    click.echo(
        f"wrote {s.path}: {s.frames} tuples ({s.train} train, {s.val} val), {s.goals} goals "
        f"({s.future_goals} future poses); {s.dropped_frames} frames without enough valid goals; {s.seconds:.1f} s\n"
        f"  {s.mix_text()}"
    )
