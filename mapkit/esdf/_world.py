"""`mapkit esdf` on a world directory: the chunked ESDF of world.zarr (`mapkit fuse-world`) → map.zarr.

Nothing world-sized is in any process: with ``unknown = occupied`` each task derives its obstacles from
its own block of world.zarr; ``free`` first marks the unseen pockets (:mod:`mapkit.esdf._pockets`) into
a scratch store beside the map, removed afterwards.
"""

from __future__ import annotations

import os
import shutil
import time
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import asdict
from pathlib import Path
from typing import Any

import numpy as np

from mapkit.esdf._chunked import signed_distance_chunked
from mapkit.esdf._pockets import free_obstacles
from mapkit.esdf._shared import (
    _CHUNK,
    _CHUNKED_DEFAULT_MAX_DIST,
    MAP,
    EsdfBuildError,
    EsdfConfig,
    EsdfSummary,
    _chunks_at_once,
    _dask_runner,
)
from mapkit.esdf._store import create_map
from mapkit.fusion import FusionError
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
    shape = (int(attrs["shape"][0]), int(attrs["shape"][1]), int(attrs["shape"][2]))
    max_dist = config.max_dist or _CHUNKED_DEFAULT_MAX_DIST
    parameters = {**asdict(config), "tsdf_voxel": attrs["fuse"]["voxel"], "chunked": True, "max_dist": max_dist,
                  "world": True}
    arrays = {name: world[name] for name in ("tsdf", "observed", "behind")}
    with _dask_runner(scheduler, workers) as runner, _scratch(directory) as scratch, create_map(
        target, shape=shape, origin=attrs["origin"], voxel_size=config.voxel, frame_id=attrs["frame_id"],
        sigma=config.sigma, unknown_policy=config.unknown, parameters=parameters, overwrite=overwrite,
    ) as writer:
        n_observed = _copy_observed(arrays["observed"], writer.observed)
        if n_observed == 0:
            raise EsdfBuildError(f"{directory / 'world.zarr'} has no observed voxel; check the flights and "
                                 "the bounds and fuse.max_depth of `mapkit fuse-world`")
        solid: Any
        if config.unknown == "occupied":
            solid = WorldSolid(arrays["tsdf"], arrays["observed"])
            n_solid = sum(int(np.count_nonzero(solid[x0 : x0 + _SLAB])) for x0 in range(0, shape[0], _SLAB))
        else:
            labels = _scratch_array(scratch, "labels", shape, "int32")
            solid = _scratch_array(scratch, "solid", shape, "bool")
            n_solid = free_obstacles(arrays, labels, solid, chunk=_CHUNK, client=runner.client, progress=progress)
        result = signed_distance_chunked(
            solid, writer.esdf, out_raw=writer.esdf_raw, voxel_size=config.voxel, max_dist=max_dist,
            sigma=config.sigma, chunk=_CHUNK, threads=runner.threads, client=runner.client, progress=progress,
            local_workers=_chunks_at_once(runner, chunk=_CHUNK, voxel=config.voxel, max_dist=max_dist,
                                          sigma=config.sigma),
        )
        writer.finalize()
    n = float(np.prod(shape))
    return EsdfSummary(target, shape, np.asarray(attrs["origin"], dtype=np.float64), config.voxel, n_observed / n,
                       n_solid / n, result.n_prevented, time.perf_counter() - t0, result)


def _check_matches(directory: Path, config: EsdfConfig, attrs: dict[str, Any]) -> None:
    """The options fixed when the world was fused must not be asked differently now."""
    if not np.isclose(config.voxel, attrs["voxel_size"]):
        raise EsdfBuildError(f"{directory} holds a world fused on a {attrs['voxel_size']} m grid; pass "
                             f"--voxel {attrs['voxel_size']} (or re-run `mapkit fuse-world --voxel {config.voxel}`)")
    if config.unknown == "free" and not np.isclose(config.solid_depth, attrs["solid_depth"]):
        raise EsdfBuildError(f"{directory} holds a world fused with solid_depth {attrs['solid_depth']}; pass "
                             f"--set solid_depth={attrs['solid_depth']} (or re-run `mapkit fuse-world`)")


def _copy_observed(observed: Any, out: Any) -> int:
    """Stream the world's observed grid into the map's (uint8) in x-slabs; returns the observed count."""
    count = 0
    for x0 in range(0, observed.shape[0], _SLAB):
        obs = np.asarray(observed[x0 : x0 + _SLAB], dtype=bool)
        out[x0 : x0 + _SLAB] = obs.astype(np.uint8)
        count += int(obs.sum())
    return count


@contextmanager
def _scratch(directory: Path) -> Iterator[Path]:
    """A scratch zarr group beside the map (on the storage the workers share), removed afterwards."""
    path = directory / f".esdf-scratch-{os.getpid()}.zarr"
    shutil.rmtree(path, ignore_errors=True)
    try:
        yield path
    finally:
        shutil.rmtree(path, ignore_errors=True)


def _scratch_array(scratch: Path, name: str, shape: tuple[int, int, int], dtype: str) -> Any:
    import zarr

    return zarr.create_array(scratch / name, shape=shape, chunks=tuple(min(64, n) for n in shape), dtype=dtype,
                             fill_value=0, zarr_format=3)
