"""`mapkit esdf` on a world directory: the chunked ESDF of world.zarr (`mapkit fuse-world`) → map.zarr.

The world's occupancy is read chunk by chunk: with ``--unknown occupied`` every task derives its
obstacles (TSDF inside, or never observed) from its own block of world.zarr, so nothing world-sized
is in any process. ``--unknown free`` also keeps unseen pockets that no observed free voxel reaches
solid, a connected-component labelling of the whole grid: that step runs in this process on dense
masks (about 8 bytes per voxel) before the chunked distances.
"""

from __future__ import annotations

import time
from dataclasses import asdict
from pathlib import Path
from typing import Any

import numpy as np

from mapkit.esdf._build import (
    _CHUNK,
    _CHUNKED_DEFAULT_MAX_DIST,
    MAP,
    EsdfBuildError,
    EsdfConfig,
    EsdfSummary,
    _dask_runner,
)
from mapkit.esdf._chunked import signed_distance_chunked
from mapkit.esdf._store import create_map
from mapkit.fusion import FusionError
from mapkit.fusion._occupancy import fill_unknown
from mapkit.fusion._world import open_world
from mapkit.workspace import check_writable

_SLAB = 64  # x-planes per streamed read (one map.zarr chunk row)


class WorldSolid:
    """The obstacles of world.zarr under ``--unknown occupied``, read block by block: a voxel is solid
    where the TSDF says inside or no ray observed it. Sliceable like a bool array; pickles as the two
    zarr arrays it reads, so Dask workers read their own blocks."""

    def __init__(self, tsdf: Any, observed: Any) -> None:
        self.tsdf, self.observed = tsdf, observed
        self.shape = tuple(int(n) for n in tsdf.shape)
        self.dtype = np.dtype(bool)

    def __getitem__(self, key: Any) -> np.ndarray:
        solid: np.ndarray = np.asarray(self.tsdf[key]) < 0
        solid |= ~np.asarray(self.observed[key], dtype=bool)
        return solid


def build_world_esdf(directory: Path, config: EsdfConfig, *, overwrite: bool, progress: bool,
                     scheduler: str | None, workers: int | None) -> EsdfSummary:
    """``directory/map.zarr`` from ``directory/world.zarr``, chunked on Dask (see :func:`build_esdf`)."""
    t0 = time.perf_counter()
    target = directory / MAP
    check_writable(target, overwrite=overwrite)
    try:
        world = open_world(directory)
    except FusionError as exc:
        raise EsdfBuildError(str(exc)) from None
    attrs = dict(world.attrs)
    _check_matches(directory, config, attrs)
    shape = tuple(int(n) for n in attrs["shape"])
    max_dist = config.max_dist or _CHUNKED_DEFAULT_MAX_DIST
    parameters = {**asdict(config), "tsdf_voxel": attrs["fuse"]["voxel"], "chunked": True, "max_dist": max_dist,
                  "world": True}
    with _dask_runner(scheduler, workers) as runner, create_map(
        target, shape=shape, origin=attrs["origin"], voxel_size=config.voxel, frame_id=attrs["frame_id"],
        sigma=config.sigma, unknown_policy=config.unknown, parameters=parameters, overwrite=overwrite,
    ) as writer:
        solid, observed_count, solid_count = _obstacles(world, config, writer.observed)
        if observed_count == 0:
            raise EsdfBuildError(f"{directory / 'world.zarr'} has no observed voxel; check the flights and "
                                 "`mapkit fuse-world --bounds / --max-depth`")
        result = signed_distance_chunked(
            solid, writer.esdf, out_raw=writer.esdf_raw, voxel_size=config.voxel, max_dist=max_dist,
            sigma=config.sigma, chunk=_CHUNK, threads=runner.threads, client=runner.client, progress=progress,
        )
        writer.finalize()
    n = float(np.prod(shape))
    return EsdfSummary(target, (shape[0], shape[1], shape[2]), np.asarray(attrs["origin"], dtype=np.float64),
                       config.voxel, observed_count / n, solid_count / n, result.n_prevented,
                       time.perf_counter() - t0, result)


def _check_matches(directory: Path, config: EsdfConfig, attrs: dict[str, Any]) -> None:
    """The options fixed when the world was fused must not be asked differently now."""
    if not np.isclose(config.voxel, attrs["voxel_size"]):
        raise EsdfBuildError(f"{directory} holds a world fused on a {attrs['voxel_size']} m grid; pass "
                             f"--voxel {attrs['voxel_size']} (or re-run `mapkit fuse-world --voxel {config.voxel}`)")
    if config.unknown == "free" and not np.isclose(config.solid_depth, attrs["solid_depth"]):
        raise EsdfBuildError(f"{directory} holds a world fused with --solid-depth {attrs['solid_depth']}; pass "
                             f"--solid-depth {attrs['solid_depth']} (or re-run `mapkit fuse-world`)")


def _obstacles(world: Any, config: EsdfConfig, out_observed: Any) -> tuple[Any, int, int]:
    """(obstacle source for the chunked ESDF, observed voxels, solid voxels); copies `observed` into the map."""
    tsdf, observed = world["tsdf"], world["observed"]
    nx = tsdf.shape[0]
    n_observed = n_solid = 0
    if config.unknown == "occupied":
        solid = WorldSolid(tsdf, observed)
        for x0 in range(0, nx, _SLAB):
            sl = slice(x0, min(x0 + _SLAB, nx))
            obs = np.asarray(observed[sl], dtype=bool)
            out_observed[sl] = obs.astype(np.uint8)
            n_observed += int(obs.sum())
            n_solid += int(np.count_nonzero(solid[sl]))
        return solid, n_observed, n_solid
    # free: the pocket rule labels connected free space over the whole grid (dense, in this process)
    obs_all = np.asarray(observed[:], dtype=bool)
    occupied = np.asarray(tsdf[:]) < 0
    dense = fill_unknown(occupied, obs_all, "free", behind=np.asarray(world["behind"][:], dtype=bool))
    del occupied
    for x0 in range(0, nx, _SLAB):
        out_observed[x0 : x0 + _SLAB] = obs_all[x0 : x0 + _SLAB].astype(np.uint8)
    return dense, int(obs_all.sum()), int(dense.sum())
