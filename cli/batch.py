"""`mapkit batch`."""

from __future__ import annotations

import sys
from typing import Any

import click

from mapkit.cli._group import COUNT, FINITE, INDEX, NONNEGATIVE, POSITIVE, library_call, main, option_values
from mapkit.cli.ingest import build_config, ingest_options


@main.command()
@click.argument("recordings", nargs=-1, required=True)
@click.option("-o", "--output", required=True, metavar="ROOT",
              help="Root folder, or an fsspec URL (s3://bucket/flights): one workspace per recording, ROOT/<name>/.")
@click.option("--steps", default="ingest,fuse,esdf,export", show_default=True, help="Steps to run, comma-separated.")
@click.option("--scheduler", metavar="ADDRESS",
              help="Dask scheduler (tcp://HOST:8786); default: DASK_SCHEDULER_ADDRESS, else a local cluster.")
@click.option("--workers", type=COUNT, default=None, help="Local cluster size (default: one per available core).")
@click.option("--retries", type=INDEX, default=1, show_default=True, help="Extra attempts of a task that raised an unexpected error.")
@click.option("--fuse-voxel", type=FINITE, default=0.05, show_default=True, help="fuse: TSDF voxel size (m).")
@click.option("--trunc", type=POSITIVE, default=4.0, show_default=True, help="fuse: TSDF truncation (voxels).")
@click.option("--max-depth", type=POSITIVE, default=8.0, show_default=True, help="fuse: ignore depth beyond this (m).")
@click.option("--mesh", is_flag=True, help="fuse: also write mesh.ply.")
@click.option("--esdf-voxel", type=FINITE, default=0.1, show_default=True, help="esdf: voxel size (m).")
@click.option("--padding", type=NONNEGATIVE, default=1.0, show_default=True, help="esdf: metres around the fused map.")
@click.option("--sigma", type=NONNEGATIVE, default=0.1, show_default=True, help="esdf: Gaussian smoothing (m); 0 = none.")
@click.option("--unknown", type=click.Choice(["free", "occupied"]), default="free", show_default=True, help="esdf: unobserved space.")
@click.option("--max-dist", type=POSITIVE, default=None, help="esdf: clamp |distance| to this (m).")
@click.option("--goals-per-frame", type=COUNT, default=5, show_default=True, help="export: goals per frame.")
@click.option("--clearance", type=NONNEGATIVE, default=0.3, show_default=True, help="export: metres every goal keeps from obstacles.")
@click.option("--seed", type=INDEX, default=0, show_default=True, help="export: seed of goal sampling and split.")
@ingest_options
@library_call
def batch(recordings: tuple[str, ...], output: str, steps: str, scheduler: str | None, workers: int | None, retries: int,
          fuse_voxel: float, trunc: float, max_depth: float, mesh: bool, esdf_voxel: float, padding: float, sigma: float,
          unknown: str, max_dist: float | None, goals_per_frame: int, clearance: float, seed: int, **kw: Any) -> None:
    """Run ingest → fuse → esdf → export for every recording: ROOT/<name>/ is the workspace the single
    commands would make. RECORDINGS are paths, globs ('flights/*.mcap') or manifests (.toml/.json with
    per-recording options; see docs/batch.md).

    Up-to-date steps are skipped, so a rerun resumes; a failed recording does not stop the others;
    exits 1 if any failed.
    """
    from mapkit.batch import BatchConfig, parse_root, parse_steps, resolve_recordings, run_batch
    from mapkit.esdf import EsdfConfig
    from mapkit.export import ExportConfig
    from mapkit.fusion import FuseConfig

    ingest_config = build_config(**kw)
    with option_values():  # the recordings and ROOT are checked apart (exit 1): their files decide
        parsed = parse_steps(steps)
        stages = (FuseConfig(voxel=fuse_voxel, trunc=trunc, max_depth=max_depth, mesh=mesh),
                  EsdfConfig(voxel=esdf_voxel, padding=padding, sigma=sigma, unknown=unknown, max_dist=max_dist),
                  ExportConfig(goals_per_frame=goals_per_frame, clearance=clearance, seed=seed))
        for stage in stages:
            stage.validate()
    fuse, esdf, export = stages
    config = BatchConfig(recordings=resolve_recordings(recordings, ingest_config), root=parse_root(output), steps=parsed,
                         scheduler=scheduler, workers=workers, retries=retries, fuse=fuse, esdf=esdf, export=export)
    summary = run_batch(config, progress=True)
    click.echo("\n".join(summary.lines()))
    if summary.failed:
        sys.exit(1)
