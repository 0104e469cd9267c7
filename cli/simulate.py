"""`mapkit simulate`: a procedural world, a UAV flight and a depth camera → a ROS recording."""

from __future__ import annotations

from pathlib import Path

import click

from mapkit.cli._group import INDEX, NONNEGATIVE, POSITIVE, Number, library_call, main, option_values


@main.command()
@click.option("--world", "world", type=click.Choice(["forest", "office", "garage"]), default="forest",
              show_default=True, help="Procedural world to fly through.")
@click.option("--seed", type=INDEX, default=0, show_default=True, help="Seed for world, flight and noise.")
@click.option("-o", "--output", "out", type=click.Path(path_type=Path), required=True,
              help="Output path; suffix optional (mcap → OUT.mcap, ros2 → OUT/, ros1 → OUT.bag).")
@click.option("--format", "fmt", type=click.Choice(["mcap", "ros2", "ros1"]), default="mcap", show_default=True,
              help="mcap: bare .mcap (ROS2 CDR, zstd); ros2: rosbag2 dir (sqlite3); ros1: .bag.")
@click.option("--duration", type=POSITIVE, default=10.0, show_default=True, help="Seconds of recording.")
@click.option("--rate", type=POSITIVE, default=30.0, show_default=True, help="Depth frame rate, Hz (odometry at 4x).")
@click.option("--width", type=Number(integer=True), default=640, show_default=True, help="Depth image width, pixels.")
@click.option("--height", type=Number(integer=True), default=480, show_default=True, help="Depth image height, pixels.")
@click.option("--noise", type=click.Choice(["none", "realsense"]), default="none", show_default=True,
              help="none: exact depth; realsense: sigma=0.0015 z^2 m, holes and edge dropouts.")
@click.option("--depth-encoding", type=click.Choice(["16UC1", "32FC1", "compressedDepth"]), default="16UC1",
              show_default=True, help="16UC1 mm / 32FC1 m Image, or compressedDepth PNG on .../compressedDepth.")
@click.option("--size", type=(float, float, float), default=None, metavar="X Y Z",
              help="World extent in metres (default per world: forest 40 40 10, office 20 14 3, garage 30 20 2.6).")
@click.option("--density", type=NONNEGATIVE, default=None,
              help="Obstacle density: forest trees/m² (0.06), office items/m² (0.05), garage bay fill (0.6).")
@click.option("--speed", type=POSITIVE, default=1.5, show_default=True, help="Cruise speed, m/s (1..3).")
@click.option("--overwrite", is_flag=True, help="Replace existing outputs (only once the new ones are complete).")
@library_call
def simulate(world: str, seed: int, out: Path, fmt: str, duration: float, rate: float, width: int, height: int,
             noise: str, depth_encoding: str, size: tuple[float, float, float] | None, density: float | None,
             speed: float, overwrite: bool) -> None:
    """Simulate a UAV depth recording with exact ground truth beside it.

    Writes the recording plus <stem>.world.json (exact primitives), <stem>.world.ply (mesh) and
    <stem>.flight.npz (stamps, poses, K).
    """
    from mapkit.sim import SimConfig
    from mapkit.sim import simulate as run

    with option_values():
        config = SimConfig(world=world, seed=seed, format=fmt, duration=duration, rate=rate, width=width,
                           height=height, noise=noise, depth_encoding=depth_encoding, size=size, density=density,
                           speed=speed, overwrite=overwrite)
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
