"""`mapkit esdf`: fused TSDF + frames → occupancy → signed, smoothed ESDF in map.zarr."""

from __future__ import annotations

import time
from dataclasses import asdict
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from mapkit import _staging
from mapkit._resources import available_memory
from mapkit.esdf._chunked import ChunkedSummary
from mapkit.esdf._shared import (
    _CHUNK,
    _CHUNKED_DEFAULT_MAX_DIST,
    MAP,
    EsdfBuildError,
    EsdfConfig,
    EsdfSummary,
    _chunks_at_once,
    _dask_runner,
    _Runner,
)
from mapkit.fusion import CLOUD, FUSE_META, TSDF, WORLD, FusionError, check_fused
from mapkit.fusion._occupancy import Grid, carve_free_space, fill_unknown, occupancy_from_tsdf
from mapkit.ingest import open_frames_store
from mapkit.workspace import FRAMES, check_writable

# Measured peaks per voxel: the dense sub-voxel path holds the EDT's distances (float64), feature
# indices and outputs; the chunked path only the masks and TSDF samples plus one chunk with halo.
_DENSE_BYTES_PER_VOXEL = 48
_CHUNKED_BYTES_PER_VOXEL = 8
_NEIGHBOURS = np.array([(a, b, c) for a in (-1, 0, 1) for b in (-1, 0, 1) for c in (-1, 0, 1)])


def subvoxel_signed_distance(
    solid: NDArray[np.bool_], surface: NDArray[np.float64], *, origin: NDArray[np.float64], voxel_size: float,
    anchor: NDArray[np.bool_] | None = None, max_dist: float | None = None, slab: int = 1 << 18,
) -> NDArray[np.float32]:
    """Signed distance measured to the fused surface points instead of to voxel centres.

    Boundary voxels are tied to the nearest surface point within one voxel; an exact EDT with feature
    transform (scipy: `edt` has none) gives each voxel its nearest boundary voxel, and the distance is
    the smallest to the points of it and its 26 neighbours. Where no point is near, the half-voxel
    convention stands in. `anchor`: the obstacles free-space distances are measured to (default
    `solid`), so solid-by-assumption space can stay negative without shortening free distances.
    """
    from scipy import ndimage
    from scipy.spatial import cKDTree

    tree = cKDTree(surface)
    shape = solid.shape
    anchor = solid if anchor is None else anchor
    out = np.empty(shape, dtype=np.float32)
    flat_out = out.reshape(-1)
    # Voxels holding surface points seed the transform too: where the centre-sampled occupancy
    # misses a thin part of an obstacle, its surface points still pull the distance to them.
    cell = np.rint((surface - origin) / voxel_size).astype(np.int64)
    inside = np.all((cell >= 0) & (cell < np.asarray(shape)), axis=1)
    has_point = np.zeros(shape, dtype=bool)
    has_point[tuple(cell[inside].T)] = True
    del cell, inside
    for region, target, sign in ((~solid, anchor, 1.0), (solid, ~solid, -1.0)):
        if not region.any():
            continue
        # Seeds: target voxels bordering the rest and voxels holding surface points, each tied to
        # its nearest surface point (none when no point is within a voxel).
        boundary = np.flatnonzero((target & ndimage.binary_dilation(~target)) | has_point)
        centres = origin + voxel_size * np.stack(np.unravel_index(boundary, shape), axis=1)
        gap, hit = tree.query(centres, distance_upper_bound=voxel_size)
        near = np.isfinite(gap)
        point_id = np.full(shape, -1, dtype=np.int32)
        point_id.reshape(-1)[boundary[near]] = np.arange(int(near.sum()), dtype=np.int32)
        points = surface[hit[near]]
        del boundary, centres, gap, hit, near
        dist, idx = ndimage.distance_transform_edt(~target & ~has_point, return_indices=True)
        nearest_xyz = [i.reshape(-1) for i in idx]
        cells = np.flatnonzero(region)
        for start in range(0, len(cells), slab):  # bounded temporaries on large grids
            part = cells[start : start + slab]
            best = _nearest_points(part, nearest_xyz, point_id, points, origin=origin, voxel_size=voxel_size)
            fallback = (dist.reshape(-1)[part] - 0.5) * voxel_size
            flat_out[part] = sign * np.where(np.isfinite(best), best, fallback)
        del dist, idx, nearest_xyz, point_id
    del has_point
    if max_dist is not None:
        np.clip(out, -max_dist, max_dist, out=out)
    return out


def _nearest_points(part: NDArray[np.int64], nearest_xyz: list[NDArray[np.int64]], point_id: NDArray[np.int32],
                    points: NDArray[np.float64], *, origin: NDArray[np.float64], voxel_size: float) -> NDArray[np.float64]:
    """Distance from the centres of the flat voxel indices ``part`` to the nearest surface point tied to
    their nearest boundary voxel or its 26 neighbours (inf where none is tied)."""
    shape = point_id.shape
    upper = np.asarray(shape) - 1
    c = origin + voxel_size * np.stack(np.unravel_index(part, shape), axis=1)
    o = np.stack([n[part] for n in nearest_xyz], axis=1)
    best = np.full(len(part), np.inf)
    for off in _NEIGHBOURS:
        q = np.clip(o + off, 0, upper)
        pid = point_id[tuple(q.T)]
        ok = pid >= 0
        d = np.full(len(part), np.inf)
        d[ok] = np.linalg.norm(c[ok] - points[pid[ok]], axis=1)
        np.minimum(best, d, out=best)
    return best


def drop_stray_obstacles(occupied: NDArray[np.bool_], surface: NDArray[np.float64], *, origin: NDArray[np.float64],
                         voxel_size: float) -> NDArray[np.bool_]:
    """Sensed obstacle voxels with a fused surface point within 1.5 voxels (the others are TSDF
    artefacts or deep inside objects: as anchors they would only shorten free-space distances)."""
    from scipy.spatial import cKDTree

    ijk = np.argwhere(occupied)
    gap, _ = cKDTree(surface).query(origin + voxel_size * ijk, distance_upper_bound=1.5 * voxel_size)
    kept = np.zeros(occupied.shape, dtype=bool)
    kept[tuple(ijk[np.isfinite(gap)].T)] = True
    return kept


def plan_grid(workspace: Path, config: EsdfConfig) -> tuple[Grid, dict[str, Any]]:
    """The ESDF grid over the fused map's bounds plus padding; errors for impossible sizes."""
    try:
        meta = check_fused(workspace)
    except FusionError as exc:
        raise EsdfBuildError(str(exc)) from None
    lo, hi = (np.asarray(b, dtype=np.float64) for b in meta["bounds"])
    extent = hi - lo
    if config.voxel > extent.max():
        raise EsdfBuildError(
            f"--voxel {config.voxel} is larger than the map itself ({extent.round(2).tolist()} m); use a smaller voxel"
        )
    grid = Grid.covering(lo - config.padding, hi + config.padding, config.voxel)
    need = grid.size * _CHUNKED_BYTES_PER_VOXEL
    have = available_memory()
    if need > 0.8 * have:
        fits = config.voxel * (need / (0.6 * have)) ** (1 / 3)
        raise EsdfBuildError(
            f"a {grid.shape[0]}x{grid.shape[1]}x{grid.shape[2]} grid ({grid.size / 1e6:.0f} M voxels) at --voxel "
            f"{config.voxel} needs about {need / 2**30:.1f} GiB but {have / 2**30:.1f} GiB is available; "
            f"use --voxel {fits:.3f} or larger"
        )
    return grid, meta


def fits_dense(grid: Grid) -> bool:
    """Whether the whole-grid (sub-voxel) computation fits in memory; else it runs chunk by chunk."""
    return grid.size * _DENSE_BYTES_PER_VOXEL < 0.5 * available_memory()


def build_esdf(workspace: str | Path, config: EsdfConfig | None = None, *, overwrite: bool = False,
               progress: bool = True, scheduler: str | None = None, workers: int | None = None,
               output: str | Path | None = None) -> EsdfSummary:
    """Build ``workspace/map.zarr`` from ``workspace/tsdf.npz`` and ``workspace/frames.zarr``, or from
    ``workspace/world.zarr`` for a world directory of ``mapkit fuse-world`` (always chunked).

    The whole grid is computed at once (sub-voxel distances) when it fits in memory. Otherwise, or
    with `scheduler` or `workers`, the chunked ESDF runs as a Dask graph on `workers` local processes
    (1 = this process) or the cluster at `scheduler` (``tcp://HOST:8786``, on storage its workers share).
    `output`: a path or fsspec URL for map.zarr instead of ``workspace/map.zarr``. `workspace` may be
    an fsspec URL (its inputs are copied to ``$TMPDIR``; :mod:`mapkit._staging`).
    """
    config = config or EsdfConfig()
    config.validate()
    if workers is not None and (isinstance(workers, bool) or workers < 1):
        raise EsdfBuildError(f"--workers {workers} must be at least 1 (1 = this process)")
    url = _staging.remote(workspace)
    if url is not None:
        return _build_at_url(url, config, overwrite=overwrite, progress=progress, scheduler=scheduler,
                             workers=workers, output=output)
    workspace = Path(workspace)
    if (workspace / WORLD).exists() and not (workspace / FUSE_META).exists():
        from mapkit.esdf._world import build_world_esdf

        if output is not None:
            raise EsdfBuildError(f"{workspace} is a world directory of `mapkit fuse-world`; its map goes to "
                                 f"{workspace / MAP} (drop --output, then `mapkit copy-store` it where it should go)")
        return build_world_esdf(workspace, config, overwrite=overwrite, progress=progress, scheduler=scheduler,
                                workers=workers)
    target = _map_target(workspace, output, overwrite=overwrite)
    t0 = time.perf_counter()
    grid, meta = plan_grid(workspace, config)
    chunked = not fits_dense(grid) or scheduler is not None or workers is not None
    # the cluster first: an unreachable scheduler fails before minutes of occupancy work
    with _dask_runner(scheduler if chunked else None, workers if chunked else None) as runner:
        fuse_cfg = meta["config"]
        occupied, solid, observed, frame_id = _occupancy(workspace, grid, fuse_cfg, config, progress=progress)
        parameters = {**asdict(config), "tsdf_voxel": fuse_cfg["voxel"]}
        summary = None
        if chunked:
            del occupied
            summary = _write_chunked(target, solid, observed, grid, config, parameters, frame_id, runner,
                                     overwrite=overwrite, progress=progress)
            prevented = summary.n_prevented
        else:
            prevented = _write_dense(workspace, target, occupied, solid, observed, grid, config, parameters, frame_id,
                                     overwrite=overwrite)
    return EsdfSummary(
        target, grid.shape, grid.origin, config.voxel, float(observed.mean()), float(solid.mean()),
        int(prevented), time.perf_counter() - t0, summary,
    )


def _occupancy(workspace: Path, grid: Grid, fuse_cfg: dict[str, Any], config: EsdfConfig, *,
               progress: bool) -> tuple[NDArray[np.bool_], NDArray[np.bool_], NDArray[np.bool_], str]:
    """(TSDF-occupied, solid after the unknown policy, observed, world frame id) on `grid`."""
    occupied, tsdf_m = occupancy_from_tsdf(
        workspace / TSDF, grid, tsdf_voxel=float(fuse_cfg["voxel"]), trunc_voxels=float(fuse_cfg["trunc"]),
    )
    seen = ~np.isnan(tsdf_m)
    del tsdf_m
    store = open_frames_store(workspace)
    observed = seen.copy()
    behind = np.zeros(grid.shape, dtype=bool) if config.unknown == "free" else None
    carve_free_space(store, grid, observed, max_depth=float(fuse_cfg["max_depth"]), behind=behind,
                     solid_depth=config.solid_depth, progress=progress)
    # A voxel some ray passed through is free unless the TSDF says inside.
    observed &= ~(occupied & ~seen)
    solid = fill_unknown(occupied, observed, config.unknown, behind=behind)
    del behind
    if solid.all() or not solid.any():
        what = "no free space" if solid.all() else "no obstacle"
        raise EsdfBuildError(
            f"the occupancy grid has {what} ({int(observed.sum())} observed voxels); check the fused map "
            f"(mapkit fuse) and unknown = {config.unknown!r}"
        )
    return occupied, solid, observed, str(store.attrs.get("world_frame", "world"))


def _map_target(workspace: Path, output: str | Path | None, *, overwrite: bool) -> Path | str:
    """map.zarr's destination, checked writable before any work: a local path, or a URL as given."""
    from mapkit._stores import Location, check_store_writable, store_errors

    if output is None:
        check_writable(workspace / MAP, overwrite=overwrite)
        return workspace / MAP
    loc = Location.of(output)
    with store_errors(loc):
        check_store_writable(loc, overwrite=overwrite)
    return loc.local if loc.local is not None else loc.url


def _write_chunked(target: Path | str, solid: NDArray[np.bool_], observed: NDArray[np.bool_], grid: Grid, config: EsdfConfig,
                   parameters: dict[str, Any], frame_id: str, runner: _Runner, *, overwrite: bool,
                   progress: bool) -> ChunkedSummary:
    """The chunked ESDF on Dask, straight into map.zarr: exact up to max_dist, half-voxel convention,
    assumed-solid space counting as obstacles for free-space distances."""
    from mapkit.esdf._chunked import signed_distance_chunked
    from mapkit.esdf._store import create_map

    max_dist = config.max_dist or _CHUNKED_DEFAULT_MAX_DIST
    parameters = {**parameters, "chunked": True, "max_dist": max_dist}
    with create_map(
        target, shape=grid.shape, origin=grid.origin, voxel_size=config.voxel, frame_id=frame_id,
        sigma=config.sigma, unknown_policy=config.unknown, parameters=parameters, overwrite=overwrite,
    ) as writer:
        result = signed_distance_chunked(
            solid, writer.esdf, out_raw=writer.esdf_raw, voxel_size=config.voxel, max_dist=max_dist,
            sigma=config.sigma, chunk=_CHUNK, threads=runner.threads, client=runner.client, progress=progress,
            local_workers=_chunks_at_once(runner, chunk=_CHUNK, voxel=config.voxel, max_dist=max_dist,
                                          sigma=config.sigma),
        )
        writer.observed[:] = observed.astype(np.uint8)
        writer.finalize()
    return result


def _write_dense(workspace: Path, target: Path | str, occupied: NDArray[np.bool_], solid: NDArray[np.bool_],
                 observed: NDArray[np.bool_], grid: Grid, config: EsdfConfig, parameters: dict[str, Any],
                 frame_id: str, *, overwrite: bool) -> int:
    """The whole-grid ESDF (sub-voxel distances unless disabled) → map.zarr; returns the sign flips prevented."""
    from mapkit.esdf._distance import signed_distance, smooth
    from mapkit.esdf._store import write_map

    if config.subvoxel:
        import open3d as o3d

        surface = np.asarray(o3d.io.read_point_cloud(workspace / CLOUD).points)
        sensed = drop_stray_obstacles(occupied, surface, origin=grid.origin, voxel_size=config.voxel)
        # free: distances to what was sensed; occupied: to unseen space as well.
        anchor = sensed if config.unknown == "free" else sensed | (solid & ~occupied)
        esdf_raw = subvoxel_signed_distance(
            solid, surface, origin=grid.origin, voxel_size=config.voxel, max_dist=config.max_dist, anchor=anchor,
        )
        del sensed, anchor
    else:
        esdf_raw = signed_distance(solid, voxel_size=config.voxel, max_dist=config.max_dist)
    esdf, prevented = smooth(esdf_raw, voxel_size=config.voxel, sigma=config.sigma)
    write_map(
        target, esdf=esdf, esdf_raw=esdf_raw, observed=observed.astype(np.uint8), origin=grid.origin,
        voxel_size=config.voxel, frame_id=frame_id, sigma=config.sigma, unknown_policy=config.unknown,
        parameters=parameters, overwrite=overwrite,
    )
    return prevented


def _build_at_url(url: str, config: EsdfConfig, *, overwrite: bool, progress: bool, scheduler: str | None,
                  workers: int | None, output: str | Path | None) -> EsdfSummary:
    """:func:`build_esdf` for a workspace at a URL, from local copies of its frames.zarr and fused files."""
    import tempfile

    if not _staging.file_set_complete(url, FUSE_META):
        raise EsdfBuildError(f"{url} has no complete fused map ({FUSE_META} and the files it lists); run "
                             f"`mapkit fuse BAG... -w {url}` first")
    with tempfile.TemporaryDirectory(prefix="mapkit-esdf-") as tmp:
        local = Path(tmp)
        _staging.download_store(url, FRAMES, local)
        _staging.download_file_set(url, FUSE_META, local)
        return build_esdf(local, config, overwrite=overwrite, progress=progress, scheduler=scheduler, workers=workers,
                          output=output if output is not None else f"{url}/{MAP}")
