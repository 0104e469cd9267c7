"""`mapkit fuse`, `mapkit fuse-world`, `mapkit esdf` and `mapkit slice`."""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, Any

import click

from mapkit._stores import Location
from mapkit.cli._group import COUNT, FINITE, NONNEGATIVE, POSITIVE, library_call, main, option_values, workspace_option
from mapkit.cli.ingest import build_config, ingest_options

if TYPE_CHECKING:
    from mapkit.esdf import Backend

FUSE_WORKSPACE = workspace_option("Workspace directory, or an fsspec URL (fused in a local temporary folder, then published there).",
                                  urls=True)
ESDF_WORKSPACE = workspace_option("Workspace directory, or an fsspec URL (built in a local temporary folder, then published there).",
                                  urls=True)
SLICE_WORKSPACE = workspace_option("Workspace with map.zarr.", urls=True)
OVERWRITE = click.option("--overwrite", is_flag=True, help="Replace existing outputs.")


@main.command()
@click.argument("recordings", nargs=-1, type=click.Path(path_type=Path))
@FUSE_WORKSPACE
@click.option("--voxel", type=FINITE, default=0.05, show_default=True, help="TSDF voxel size (m).")
@click.option("--trunc", type=POSITIVE, default=4.0, show_default=True, help="TSDF truncation (voxels).")
@click.option("--max-depth", type=POSITIVE, default=8.0, show_default=True, help="Ignore depth beyond this (m).")
@click.option("--device", default="cpu", show_default=True, help="cpu or cuda:N.")
@click.option("--frame-stride", "frame_stride", type=COUNT, default=1, show_default=True, help="Integrate every N-th frame.")
@click.option("--mesh", is_flag=True, help="Also write WS/mesh.ply (marching cubes).")
@OVERWRITE
@ingest_options
@library_call
def fuse(recordings: tuple[Path, ...], workspace: Path, voxel: float, trunc: float, max_depth: float, device: str,
         frame_stride: int, mesh: bool, overwrite: bool, **kw: Any) -> None:
    """TSDF-fuse RECORDINGS (or WS/frames.zarr when none are given) into WS/cloud.ply.

    Ingests first unless WS/frames.zarr is up to date for the same recordings and options.
    """
    from mapkit.fusion import FuseConfig
    from mapkit.fusion import fuse as fuse_fn

    with option_values():
        config = FuseConfig(voxel=voxel, trunc=trunc, max_depth=max_depth, device=device, stride=frame_stride, mesh=mesh)
        config.validate()
    s = fuse_fn(list(recordings), workspace, config, build_config(**kw), overwrite=overwrite, progress=True)
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
@click.option("--voxel", type=FINITE, default=0.1, show_default=True, help="World grid (= ESDF) voxel size (m).")
@click.option("--tsdf-voxel", type=FINITE, default=0.05, show_default=True, help="TSDF voxel size (m), as mapkit fuse --voxel.")
@click.option("--trunc", type=POSITIVE, default=4.0, show_default=True, help="TSDF truncation (voxels).")
@click.option("--max-depth", type=POSITIVE, default=8.0, show_default=True, help="Ignore depth beyond this (m).")
@click.option("--frame-stride", "frame_stride", type=COUNT, default=1, show_default=True, help="Integrate every N-th frame.")
@click.option("--padding", type=NONNEGATIVE, default=1.0, show_default=True, help="Metres around the bounds.")
@click.option("--solid-depth", type=NONNEGATIVE, default=0.5, show_default=True,
              help="Unseen space this far (m) behind measured surfaces is marked solid-behind (mapkit esdf --unknown free).")
@click.option("--tile", type=COUNT, default=128, show_default=True, help="Voxels per tile edge (a multiple of 64); one Dask task each.")
@click.option("--bounds", type=FINITE, nargs=6, default=None, metavar="X0 Y0 Z0 X1 Y1 Z1",
              help="World box (m); default: the flights' depth points.")
@click.option("--scheduler", metavar="ADDRESS",
              help="Dask scheduler (tcp://HOST:8786; default: DASK_SCHEDULER_ADDRESS); paths must be on storage the workers share.")
@click.option("--workers", type=COUNT, default=None, help="N local Dask worker processes (default: 1, this process).")
@OVERWRITE
@library_call
def fuse_world_cmd(workspaces: tuple[Path, ...], output: Path, voxel: float, tsdf_voxel: float, trunc: float,
                   max_depth: float, frame_stride: int, padding: float, solid_depth: float, tile: int,
                   bounds: tuple[float, ...] | None, scheduler: str | None, workers: int | None, overwrite: bool) -> None:
    """Fuse the flights of WORKSPACES (each with frames.zarr, one world frame) into one world map,
    tile by tile on Dask: OUTPUT/world.zarr, the chunked occupancy `mapkit esdf -w OUTPUT` reads.

    With one workspace the result equals `mapkit fuse` + `mapkit esdf --workers 1` on the same grid.
    """
    from mapkit._dask import scheduler_address
    from mapkit.fusion import FuseConfig, WorldConfig, fuse_world

    box = None if bounds is None else ((bounds[0], bounds[1], bounds[2]), (bounds[3], bounds[4], bounds[5]))
    with option_values():
        config = WorldConfig(voxel=voxel, padding=padding, tile=tile, solid_depth=solid_depth, bounds=box,
                             fuse=FuseConfig(voxel=tsdf_voxel, trunc=trunc, max_depth=max_depth, stride=frame_stride))
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
@click.option("--voxel", type=FINITE, default=0.1, show_default=True, help="ESDF voxel size (m).")
@click.option("--padding", type=NONNEGATIVE, default=1.0, show_default=True, help="Metres around the fused map.")
@click.option("--sigma", type=NONNEGATIVE, default=0.1, show_default=True, help="Gaussian smoothing (m); 0 = none.")
@click.option("--unknown", type=click.Choice(["free", "occupied"]), default="free", show_default=True,
              help="Unobserved space: free (as the paper; enclosed unseen pockets stay solid) or occupied (conservative).")
@click.option("--solid-depth", type=NONNEGATIVE, default=0.5, show_default=True,
              help="With --unknown free: unseen space this far (m) behind measured surfaces is solid.")
@click.option("--max-dist", type=POSITIVE, default=None, help="Clamp |distance| to this (m).")
@click.option("--backend", type=click.Choice(["edt", "scipy"]), default="edt", show_default=True, help="Exact EDT implementation.")
@click.option("--scheduler", metavar="ADDRESS",
              help="Compute the chunked ESDF on this Dask scheduler (tcp://HOST:8786; default: DASK_SCHEDULER_ADDRESS); "
                   "the workspace must be on storage the workers share.")
@click.option("--workers", type=COUNT, default=None,
              help="Compute the chunked ESDF on N local Dask worker processes (1 = in this process).")
@click.option("-o", "--output", metavar="PATH|URL", default=None,
              help="Write map.zarr here instead of WS/map.zarr: a path or an fsspec URL (s3://bucket/site/map.zarr).")
@OVERWRITE
@library_call
def esdf(workspace: Path, voxel: float, padding: float, sigma: float, unknown: str, solid_depth: float,
         max_dist: float | None, backend: Backend, scheduler: str | None, workers: int | None, output: str | None,
         overwrite: bool) -> None:
    """Signed, Gaussian-smoothed ESDF of the fused map → WS/map.zarr.

    Grids too large for memory, or any grid with --workers / --scheduler, are computed chunk by chunk
    as a Dask graph (exact up to --max-dist, default 2 m there).
    """
    from mapkit._dask import scheduler_address
    from mapkit.esdf import EsdfConfig, build_esdf

    with option_values():
        config = EsdfConfig(voxel=voxel, padding=padding, sigma=sigma, unknown=unknown, solid_depth=solid_depth,
                            max_dist=max_dist, backend=backend)
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
