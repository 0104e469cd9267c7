"""`mapkit simulate`: a procedural world, a UAV flight and a depth camera → a ROS recording."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import click

from mapkit.cli._config import ConfigSpec, Settings, config_options, field_option
from mapkit.cli._group import INDEX, POSITIVE, library_call, main, option_values


def _defaults() -> Any:
    from mapkit.sim import SimConfig

    return SimConfig()


SIMULATE = ConfigSpec("simulate", (("", _defaults),), hidden=frozenset({"overwrite"}), example="noise=realsense")


@main.command()
@field_option("--world", "world", spec=SIMULATE, key="world", type=click.Choice(["forest", "office", "garage"]),
              help="Procedural world to fly through.")
@field_option("--seed", spec=SIMULATE, key="seed", type=INDEX)
@click.option("-o", "--output", "out", type=click.Path(path_type=Path), required=True,
              help="Output path; suffix optional (mcap → OUT.mcap, ros2 → OUT/, ros1 → OUT.bag).")
@field_option("--format", "fmt", spec=SIMULATE, key="format", type=click.Choice(["mcap", "ros2", "ros1"]),
              help="mcap: bare .mcap (ROS2 CDR, zstd); ros2: rosbag2 dir (sqlite3); ros1: .bag.")
@field_option("--duration", spec=SIMULATE, key="duration", type=POSITIVE)
@field_option("--overwrite", spec=SIMULATE, key="overwrite", is_flag=True)
@config_options(SIMULATE)
@library_call
def simulate(world: str | None, seed: int | None, out: Path, fmt: str | None, duration: float | None,
             overwrite: bool | None, settings: Settings) -> None:
    """Simulate a UAV depth recording with exact ground truth beside it.

    Writes the recording plus <stem>.world.json (exact primitives), <stem>.world.ply (mesh) and
    <stem>.flight.npz (stamps, poses, K). The camera (rate, width, height, noise, depth encoding), the
    world's size and density and the flight's speed are settings: `mapkit config simulate`.
    """
    from mapkit.sim import simulate as run

    with option_values():
        config = settings.build(_defaults(), {"world": world, "seed": seed, "format": fmt, "duration": duration,
                                              "overwrite": overwrite})
        config.validate()
    result = run(config, out, progress=True)
    size_bytes = _size(result.bag_path)
    click.echo(
        f"{len(result.stamps_ns)} frames, {result.duration:.2f} s, path {result.path_length:.1f} m, "
        f"{size_bytes / 1e6:.2f} MB"
    )
    for p in result.paths:
        click.echo(f"  {p}")


def _size(path: Path) -> int:
    if path.is_dir():
        return sum(f.stat().st_size for f in path.rglob("*") if f.is_file())
    return path.stat().st_size
