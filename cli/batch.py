"""`mapkit batch`."""

from __future__ import annotations

import dataclasses
import sys
from pathlib import Path
from typing import Any

import click

from mapkit.cli._config import ConfigSpec, Settings, config_options, field_option
from mapkit.cli._group import COUNT, library_call, main, option_values
from mapkit.cli.ingest import INGEST_CODECS, INGEST_TABLE, build_config, ingest_options


def _defaults() -> Any:
    """BatchConfig's settings (its recordings and root are the command's arguments)."""
    from mapkit.batch import BatchConfig

    return BatchConfig(recordings=(), root=Path("."))


BATCH = ConfigSpec("batch", (("", _defaults), INGEST_TABLE), codecs=INGEST_CODECS, example="esdf.sigma=0.2")


@main.command()
@click.argument("recordings", nargs=-1, required=True)
@click.option("-o", "--output", required=True, metavar="ROOT",
              help="Root folder, or an fsspec URL (s3://bucket/flights): one workspace per recording, ROOT/<name>/.")
@field_option("--steps", spec=BATCH, key="steps", help="Steps to run, comma-separated.")
@field_option("--scheduler", spec=BATCH, key="scheduler", metavar="ADDRESS",
              help="Dask scheduler (tcp://HOST:8786); default: DASK_SCHEDULER_ADDRESS, else a local cluster.")
@field_option("--workers", spec=BATCH, key="workers", type=COUNT,
              help="Local cluster size (default: one per available core).")
@ingest_options(BATCH)
@config_options(BATCH)
@library_call
def batch(recordings: tuple[str, ...], output: str, steps: str | None, scheduler: str | None, workers: int | None,
          settings: Settings, **kw: Any) -> None:
    """Run ingest → fuse → esdf → export for every recording: ROOT/<name>/ is the workspace the single
    commands would make. RECORDINGS are paths, globs ('flights/*.mcap') or manifests (.toml/.json with
    per-recording options; see docs/batch.md). Each step's settings are a table (fuse.voxel,
    esdf.sigma, export.seed, ingest.stride, ...): `mapkit config batch`.

    Up-to-date steps are skipped, so a rerun resumes; a failed recording does not stop the others;
    exits 1 if any failed.
    """
    from mapkit.batch import parse_root, parse_steps, resolve_recordings, run_batch

    ingest_config = build_config(settings, **kw)
    with option_values():  # the recordings and ROOT are checked apart (exit 1): their files decide
        options = {"steps": parse_steps(steps) if steps is not None else None, "scheduler": scheduler,
                   "workers": workers}
        settled = settings.build(_defaults(), options)
        for stage in (settled.fuse, settled.esdf, settled.export):
            stage.validate()
    config = dataclasses.replace(settled, recordings=resolve_recordings(recordings, ingest_config), root=parse_root(output))
    summary = run_batch(config, progress=True)
    click.echo("\n".join(summary.lines()))
    if summary.failed:
        sys.exit(1)
