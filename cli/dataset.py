"""`mapkit dataset`."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import click

from mapkit.cli._config import Codec, ConfigSpec, Settings, config_options, field_option
from mapkit.cli._group import COUNT, INDEX, library_call, main, option_values


def _defaults() -> Any:
    from mapkit.dataset import DatasetConfig

    return DatasetConfig()


def _read_cameras(value: Any) -> Any:
    from mapkit.dataset import parse_cameras

    if isinstance(value, list) and all(isinstance(v, str) for v in value):
        value = ",".join(value)
    if not isinstance(value, str):
        raise ValueError('expected cameras as text, WIDTHxHEIGHT[:FX_SCALE] separated by commas (e.g. "160x120,212x120:1.1")')
    return parse_cameras(value)


def _show_cameras(cameras: Any) -> str:
    return ",".join(f"{c.width}x{c.height}" + (f":{c.fx_scale:g}" if c.fx_scale != 1.0 else "") for c in cameras)


DATASET = ConfigSpec("dataset", (("", _defaults),), codecs={"cameras": Codec(_read_cameras, _show_cameras)},
                     example="cameras=640x360")


@main.command("dataset")
@click.option("-o", "--output", "root", required=True, type=click.Path(path_type=Path),
              help="Directory of the dataset: one workspace per world plus dataset.json.")
@field_option("--worlds", spec=DATASET, key="worlds", type=COUNT)
@field_option("--seed", spec=DATASET, key="seed", type=INDEX, help="World i gets simulator seed SEED+i.")
@field_option("--workers", spec=DATASET, key="workers", type=INDEX)
@click.option("--dry-run", is_flag=True, help="Print the size/time estimate and the world list, generate nothing.")
@config_options(DATASET)
@library_call
def dataset_cmd(root: Path, worlds: int | None, seed: int | None, workers: int | None, dry_run: bool,
                settings: Settings) -> None:
    """Many simulated worlds (varied kinds, density, size, speed, camera, mount pitch, noise), each
    flown and run through ingest → fuse → esdf → export into ROOT/<world>/. Resumable: complete
    worlds are skipped. The ranges worlds are drawn from, the cameras and the goal mix
    (export.goal_mix) are settings: `mapkit config dataset`."""
    from mapkit.dataset import build_dataset, world_specs

    with option_values():
        config = settings.build(_defaults(), {"worlds": worlds, "seed": seed, "workers": workers})
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
