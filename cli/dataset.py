"""`mapkit dataset`."""

from __future__ import annotations

from pathlib import Path

import click

from mapkit.cli._group import COUNT, INDEX, NONNEGATIVE, POSITIVE, library_call, main, option_values


@main.command("dataset")
@click.option("-o", "--output", "root", required=True, type=click.Path(path_type=Path),
              help="Directory of the dataset: one workspace per world plus dataset.json.")
@click.option("--worlds", type=COUNT, default=24, show_default=True, help="Number of worlds (one flight each).")
@click.option("--kinds", default="forest,office,garage", show_default=True, help="World kinds, used in turn.")
@click.option("--seed", type=INDEX, default=1000, show_default=True, help="World i gets simulator seed SEED+i.")
@click.option("--duration", type=POSITIVE, default=40.0, show_default=True, help="Seconds of flight per world.")
@click.option("--rate", type=POSITIVE, default=5.0, show_default=True, help="Depth frames per second.")
@click.option("--goals-per-frame", type=COUNT, default=5, show_default=True, help="Goals per exported frame.")
@click.option("--goal-mix", type=NONNEGATIVE, nargs=3, default=(0.2, 0.4, 0.4), show_default=True,
              help="Shares of FUTURE VISIBLE HIDDEN goals.")
@click.option("--speed", type=POSITIVE, nargs=2, default=(1.0, 2.5), show_default=True,
              help="Range of each world's cruise speed, m/s (MIN MAX, within 1..3).")
@click.option("--density-scale", type=POSITIVE, nargs=2, default=(0.8, 1.8), show_default=True,
              help="Range of obstacle density relative to each kind's default (MIN MAX).")
@click.option("--size-scale", type=POSITIVE, nargs=2, default=(0.55, 0.8), show_default=True,
              help="Range of horizontal world extent relative to each kind's default (MIN MAX).")
@click.option("--tilt-deg", type=NONNEGATIVE, nargs=2, default=(0.0, 15.0), show_default=True,
              help="Range of camera pitch down, degrees (MIN MAX; world 0 flies level).")
@click.option("--cameras", default="160x120,212x120:1.1,192x144:0.9", show_default=True,
              help="Depth cameras drawn per world, WIDTHxHEIGHT[:FX_SCALE] (focal length relative to a D435's); "
                   "world 0 flies the first, and `mapkit eval` renders it. 640x360 for the paper preset.")
@click.option("--noise-fraction", type=NONNEGATIVE, default=0.5, show_default=True,
              help="Share of worlds recorded with RealSense-like depth noise.")
@click.option("--workers", type=INDEX, default=0, show_default=True, help="Worlds at once (0 = one per CPU core).")
@click.option("--dry-run", is_flag=True, help="Print the size/time estimate and the world list, generate nothing.")
@library_call
def dataset_cmd(root: Path, worlds: int, kinds: str, seed: int, duration: float, rate: float, goals_per_frame: int,
                goal_mix: tuple[float, float, float], speed: tuple[float, float], density_scale: tuple[float, float],
                size_scale: tuple[float, float], tilt_deg: tuple[float, float], cameras: str, noise_fraction: float,
                workers: int, dry_run: bool) -> None:
    """Many simulated worlds (varied kinds, density, size, speed, camera, mount pitch, noise), each
    flown and run through ingest → fuse → esdf → export into ROOT/<world>/. Resumable: complete
    worlds are skipped."""
    from mapkit.dataset import DatasetConfig, build_dataset, parse_cameras, world_specs
    from mapkit.export import ExportConfig

    with option_values():
        config = DatasetConfig(worlds=worlds, kinds=tuple(k.strip() for k in kinds.split(",") if k.strip()), seed=seed,
                               duration=duration, rate=rate, speed=speed, density_scale=density_scale,
                               size_scale=size_scale, tilt_deg=tilt_deg, cameras=parse_cameras(cameras),
                               noise_fraction=noise_fraction, workers=workers,
                               export=ExportConfig(goals_per_frame=goals_per_frame, goal_mix=goal_mix))
        config.validate()
    s = build_dataset(root, config, progress=True, dry_run=dry_run)
    if dry_run:
        for spec in world_specs(config):
            click.echo(f"  {spec.name}: {spec.size[0]}x{spec.size[1]}x{spec.size[2]} m, density {spec.density}, "
                       f"{spec.speed} m/s, camera {spec.width}x{spec.height} fx {spec.fx} tilt {spec.tilt_deg} deg, "
                       f"noise {spec.noise}")
        return
    click.echo(f"dataset {s.root}: {len(s.done)} built, {len(s.skipped)} already complete, {len(s.failed)} failed; "
               f"{s.frames} frames, {s.tuples} tuples in {s.seconds / 60:.1f} min")
    for name, reason in s.failed.items():
        click.echo(f"  failed {name}: {reason}", err=True)
    if s.failed:
        raise SystemExit(1)
