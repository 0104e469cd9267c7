"""`mapkit fuse`, `mapkit fuse-world`, `mapkit esdf` and `mapkit slice`."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import click

from mapkit._stores import Location
from mapkit.cli._config import ConfigSpec, Settings, config_options, field_option
from mapkit.cli._group import COUNT, FINITE, library_call, main, option_values, workspace_option
from mapkit.cli.ingest import INGEST_CODECS, INGEST_TABLE, build_config, ingest_options

FUSE_WORKSPACE = workspace_option("Workspace directory, or an fsspec URL (fused in a local temporary folder, then published there).",
                                  urls=True)
ESDF_WORKSPACE = workspace_option("Workspace directory, or an fsspec URL (built in a local temporary folder, then published there).",
                                  urls=True)
SLICE_WORKSPACE = workspace_option("Workspace with map.zarr.", urls=True)
OVERWRITE = click.option("--overwrite", is_flag=True, help="Replace existing outputs.")


def _fuse_defaults() -> Any:
    from mapkit.fusion import FuseConfig

    return FuseConfig()


def _world_defaults() -> Any:
    from mapkit.fusion import WorldConfig

    return WorldConfig()


def _esdf_defaults() -> Any:
    from mapkit.esdf import EsdfConfig

    return EsdfConfig()


FUSE = ConfigSpec("fuse", (("", _fuse_defaults), INGEST_TABLE), codecs=INGEST_CODECS, example="max_depth=6")
FUSE_WORLD = ConfigSpec("fuse-world", (("", _world_defaults),), example="fuse.voxel=0.05")
ESDF = ConfigSpec("esdf", (("", _esdf_defaults),), example="unknown=occupied")


@main.command()
@click.argument("recordings", nargs=-1, type=click.Path(path_type=Path))
@FUSE_WORKSPACE
@field_option("--voxel", spec=FUSE, key="voxel", type=FINITE, help="TSDF voxel size (m).")
@field_option("--mesh", spec=FUSE, key="mesh", is_flag=True, help="Also write WS/mesh.ply (marching cubes).")
@field_option("--device", spec=FUSE, key="device", help="cpu or cuda:N.")
@OVERWRITE
@ingest_options(FUSE)
@config_options(FUSE)
@library_call
def fuse(recordings: tuple[Path, ...], workspace: Path, voxel: float | None, mesh: bool | None, device: str | None,
         overwrite: bool, settings: Settings, **kw: Any) -> None:
    """TSDF-fuse RECORDINGS (or WS/frames.zarr when none are given) into WS/cloud.ply.

    Ingests first unless WS/frames.zarr is up to date for the same recordings and options. Every
    setting (truncation, max depth, frame stride, ingest.*): `mapkit config fuse`.
    """
    from mapkit.fusion import fuse as fuse_fn

    with option_values():
        config = settings.build(_fuse_defaults(), {"voxel": voxel, "mesh": mesh, "device": device})
        config.validate()
    s = fuse_fn(list(recordings), workspace, config, build_config(settings, **kw), overwrite=overwrite, progress=True)
    dropped = ", ".join(f"{k} {v}" for k, v in s.dropped.items()) or "none"
    lo, hi = s.bounds
    click.echo(
        f"fused {s.frames_used} of {s.frames_total} frames (dropped at ingest: {dropped}); {s.blocks} blocks, "
        f"{s.voxels / 1e6:.1f} M voxels, {s.points} points; bounds [{lo[0]:.2f} {lo[1]:.2f} {lo[2]:.2f}] – "
        f"[{hi[0]:.2f} {hi[1]:.2f} {hi[2]:.2f}] m; {s.seconds:.1f} s ({s.frames_per_second:.0f} frames/s, "
        f"integrate {s.integrate_frames_per_second:.0f} frames/s)"
    )
    click.echo("wrote " + ", ".join(s.urls or [str(p) for p in s.outputs]))


@main.command("fuse-world")
@click.argument("workspaces", nargs=-1, required=True, type=click.Path(path_type=Path))
@click.option("-o", "--output", type=click.Path(path_type=Path), required=True,
              help="World directory: OUTPUT/world.zarr (then `mapkit esdf -w OUTPUT`).")
@field_option("--voxel", spec=FUSE_WORLD, key="voxel", type=FINITE, help="World grid (= ESDF) voxel size (m).")
@click.option("--scheduler", metavar="ADDRESS",
              help="Dask scheduler (tcp://HOST:8786; default: DASK_SCHEDULER_ADDRESS); paths must be on storage the workers share.")
@click.option("--workers", type=COUNT, default=None, help="N local Dask worker processes (default: 1, this process).")
@OVERWRITE
@config_options(FUSE_WORLD)
@library_call
def fuse_world_cmd(workspaces: tuple[Path, ...], output: Path, voxel: float | None, scheduler: str | None,
                   workers: int | None, overwrite: bool, settings: Settings) -> None:
    """Fuse the flights of WORKSPACES (each with frames.zarr, one world frame) into one world map,
    tile by tile on Dask: OUTPUT/world.zarr, the chunked occupancy `mapkit esdf -w OUTPUT` reads.

    With one workspace the result equals `mapkit fuse` + `mapkit esdf --workers 1` on the same grid.
    The TSDF (fuse.voxel, fuse.trunc, ...), tiles and bounds are settings: `mapkit config fuse-world`.
    """
    from mapkit._dask import scheduler_address
    from mapkit.fusion import fuse_world

    with option_values():
        config = settings.build(_world_defaults(), {"voxel": voxel})
        config.validate()
    s = fuse_world(list(workspaces), output, config, overwrite=overwrite, progress=True,
                   scheduler=scheduler_address(scheduler), workers=workers)
    nx, ny, nz = s.shape
    click.echo(
        f"wrote {s.path}: {nx}x{ny}x{nz} voxels of {s.voxel_size} m, origin {s.origin.round(3).tolist()}; "
        f"{s.tiles_fused} of {s.tiles} tiles reached by {s.frames} frames, on {s.workers} Dask worker(s), peak memory "
        f"per worker {s.peak_rss_bytes / 2**30:.2f} GiB; {s.seconds:.1f} s"
    )


@main.command()
@ESDF_WORKSPACE
@field_option("--voxel", spec=ESDF, key="voxel", type=FINITE, help="ESDF voxel size (m).")
@click.option("--scheduler", metavar="ADDRESS",
              help="Compute the chunked ESDF on this Dask scheduler (tcp://HOST:8786; default: DASK_SCHEDULER_ADDRESS); "
                   "the workspace must be on storage the workers share.")
@click.option("--workers", type=COUNT, default=None,
              help="Compute the chunked ESDF on N local Dask worker processes (1 = in this process).")
@click.option("-o", "--output", metavar="PATH|URL", default=None,
              help="Write map.zarr here instead of WS/map.zarr: a path or an fsspec URL (s3://bucket/site/map.zarr).")
@OVERWRITE
@config_options(ESDF)
@library_call
def esdf(workspace: Path, voxel: float | None, scheduler: str | None, workers: int | None, output: str | None,
         overwrite: bool, settings: Settings) -> None:
    """Signed, Gaussian-smoothed ESDF of the fused map → WS/map.zarr.

    Grids too large for memory, or any grid with --workers / --scheduler, are computed chunk by chunk
    as a Dask graph (exact up to max_dist, default 2 m there). Padding, smoothing, unseen space and
    the rest are settings: `mapkit config esdf`.
    """
    from mapkit._dask import scheduler_address
    from mapkit.esdf import build_esdf

    with option_values():
        config = settings.build(_esdf_defaults(), {"voxel": voxel})
        config.validate()
    s = build_esdf(workspace, config, overwrite=overwrite, progress=True, scheduler=scheduler_address(scheduler),
                   workers=workers, output=output)
    nx, ny, nz = s.shape
    ran = ""
    if s.chunked is not None:
        c = s.chunked
        ran = (f"; {c.chunks} chunks (halo {c.halo}) on {c.workers} Dask worker(s), peak memory per worker "
               f"{c.peak_rss_bytes / 2**30:.2f} GiB")
    click.echo(
        f"wrote {s.path}: {nx}x{ny}x{nz} voxels of {s.voxel_size} m, origin {s.origin.round(3).tolist()}; "
        f"observed {100 * s.observed_fraction:.1f} %, obstacles {100 * s.occupied_fraction:.1f} %; "
        f"smoothing sign flips prevented: {s.sign_flips_prevented}{ran}; {s.seconds:.1f} s"
    )


def _parse_slices(tokens: tuple[str, ...]) -> dict[str, list[float]]:
    """`--z 1.0 2.5 --x -3` → {"z": [1.0, 2.5], "x": [-3.0], "y": []} (click options take one value)."""
    out: dict[str, list[float]] = {"x": [], "y": [], "z": []}
    axis = None
    for token in tokens:
        if token in ("--x", "--y", "--z"):
            axis = token[2:]
            continue
        try:
            value = float(token)
        except ValueError:
            raise click.UsageError(f"unexpected {token!r}; use --z Z [Z ...], --x X [...], --y Y [...]") from None
        if axis is None:
            raise click.UsageError(f"value {token} comes before any of --z/--x/--y")
        out[axis].append(value)
    if not any(out.values()):
        raise click.UsageError("give at least one slice: --z Z [Z ...], --x X [...] or --y Y [...]")
    return out


@main.command("slice", context_settings={"ignore_unknown_options": True})
@SLICE_WORKSPACE
@click.option("-o", "--output", type=click.Path(path_type=Path), default=Path("slices.png"), show_default=True, help="PNG to write.")
@click.option("--raw", is_flag=True, help="Show the unsmoothed distance (esdf_raw).")
@click.argument("positions", nargs=-1, type=click.UNPROCESSED, metavar="--z Z [Z ...] | --x X [X ...] | --y Y [Y ...]")
@library_call
def slice_cmd(workspace: Path | str, output: Path, raw: bool, positions: tuple[str, ...]) -> None:
    """PNG of ESDF slices at the given heights / positions (m), with a colour bar and metric axes.

    Example: mapkit slice -w WS --z 1.0 2.5 3.5 -o slices.png
    """
    from mapkit.esdf import MAP, EsdfMap, render_slices

    axes = _parse_slices(positions)
    path = render_slices(EsdfMap.open(Location.of(workspace) / MAP), z=axes["z"], x=axes["x"], y=axes["y"], path=output, raw=raw)
    click.echo(f"wrote {path}")
