"""Many flights → one world map, tile by tile on Dask → world.zarr, the chunked occupancy the ESDF reads.

One task per tile integrates, in flight and frame order, every frame that can reach the tile into a
TSDF holding only the tile's blocks, samples it at the tile's voxel centres and carves its observed /
behind-surface voxels: bit for bit what `mapkit fuse` + `mapkit esdf` compute there, with nothing
world-sized in one process. Layout of ``world.zarr``: docs/data_contracts.md.
"""

from __future__ import annotations

import math
import os
import resource
import time
import warnings
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import NDArray

from mapkit._version import __version__
from mapkit.fusion._occupancy import Grid, Window, carve_free_space, sample_tsdf
from mapkit.fusion._tsdf import (
    BLOCK_RESOLUTION,
    FuseConfig,
    FusionError,
    _o3c_tensor,
    _o3d_depth,
    _o3d_intrinsics,
    _o3d_ready,
    _touched_blocks,
    _tsdf_grid,
)
from mapkit.geometry import invert_transform
from mapkit.ingest import FramesStore, open_frames_store
from mapkit.workspace import atomic_output, check_writable

if TYPE_CHECKING:
    from distributed import Client

WORLD = "world.zarr"
KIND = "mapkit.world"
CHUNK = 64
_MAX_BOUND_FRAMES = 60  # frames per flight sampled for the world's bounds
_MAX_TILE_BLOCKS = 1 << 18  # TSDF hash map capacity cap per tile (it grows if a tile needs more)


@dataclass(frozen=True)
class WorldConfig:
    """Options of `mapkit fuse-world`: each field is a setting (`mapkit config fuse-world`)."""

    voxel: float = 0.1
    """Voxel of the world grid in metres: the ESDF's voxel (`mapkit esdf --voxel` must match)."""
    padding: float = 1.0
    """Metres added around the bounds."""
    tile: int = 128
    """Voxels per tile edge (a multiple of 64): one Dask task each."""
    solid_depth: float = 0.5
    """Unobserved space up to this far (metres) behind measured surfaces is marked `behind`
    (`mapkit esdf`'s ``solid_depth`` must match)."""
    bounds: tuple[tuple[float, float, float], tuple[float, float, float]] | None = None
    """World box [lo, hi] in metres; default: the depth points of the flights (about the fused
    surface's bounds, which `mapkit fuse` uses)."""
    fuse: FuseConfig = field(default_factory=FuseConfig)
    """TSDF options (voxel, truncation, max depth, frame stride), as `mapkit fuse`."""

    def validate(self) -> None:
        self.fuse.validate()
        if not self.voxel > 0:
            raise FusionError(f"--voxel {self.voxel} must be positive (metres, e.g. 0.1)")
        if self.padding < 0:
            raise FusionError(f"padding {self.padding} must be >= 0 metres")
        if self.solid_depth < 0:
            raise FusionError(f"solid_depth {self.solid_depth} must be >= 0 metres")
        if isinstance(self.tile, bool) or self.tile < CHUNK or self.tile % CHUNK:
            raise FusionError(f"tile {self.tile} must be a positive multiple of {CHUNK} voxels (e.g. 128)")
        if self.bounds is not None:
            lo, hi = np.asarray(self.bounds[0], float), np.asarray(self.bounds[1], float)
            if lo.shape != (3,) or hi.shape != (3,) or not np.all(np.isfinite(lo) & np.isfinite(hi)) or np.any(hi <= lo):
                raise FusionError(f"bounds {self.bounds}: expected [[x0, y0, z0], [x1, y1, z1]] with x1 > x0, y1 > y0, z1 > z0")


@dataclass(frozen=True)
class WorldSummary:
    """What :func:`fuse_world` did."""

    path: Path
    """The world.zarr written."""
    shape: tuple[int, int, int]
    """World grid [nx, ny, nz]."""
    origin: NDArray[np.float64]
    """Centre of voxel [0, 0, 0], metres."""
    voxel_size: float
    """Metres."""
    tiles: int
    """Tiles of the grid."""
    tiles_fused: int
    """Tiles some frame can reach (the others stay unobserved)."""
    frames: int
    """Frames of all flights."""
    workers: int
    """Processes that ran tiles."""
    peak_rss_bytes: int
    """Largest peak resident memory of a process that ran tiles."""
    seconds: float
    """Wall time."""


@dataclass(frozen=True)
class _Tile:
    """One tile's task input: its window and, per flight, the frames that can reach it."""

    window: Window
    frames: tuple[tuple[int, ...], ...]


def fuse_world(workspaces: Sequence[str | Path], output: str | Path, config: WorldConfig | None = None, *,
               overwrite: bool = False, progress: bool = True, scheduler: str | None = None,
               workers: int | None = None) -> WorldSummary:
    """Fuse the frames.zarr of every workspace (flights in one world frame) into ``output/world.zarr``,
    one Dask task per tile: in this process (`workers` None or 1), on a local cluster of `workers`
    processes, or on the cluster at `scheduler` (on storage the workers share)."""
    from mapkit._dask import compute_tasks

    config = config or WorldConfig()
    config.validate()
    if workers is not None and (isinstance(workers, bool) or workers < 1):
        raise FusionError(f"--workers {workers} must be at least 1 (1 = this process)")
    t0 = time.perf_counter()
    stores = _open_stores(workspaces)
    frame_id = _world_frame(stores)
    target = Path(output) / WORLD
    check_writable(target, overwrite=overwrite)
    if config.bounds is not None:
        lo, hi = (np.asarray(b, dtype=np.float64) for b in config.bounds)
    else:
        lo, hi = _depth_bounds(stores, config.fuse)
    grid = Grid.covering(lo - config.padding, hi + config.padding, config.voxel)
    tiles = _plan_tiles(grid, stores, config)
    fused = [t for t in tiles if any(t.frames)]
    with _client(scheduler, workers) as client, _world_store(target, grid, frame_id, config, stores,
                                                             overwrite=overwrite) as arrays:
        import dask

        task = dask.delayed(_tile_task, pure=False)
        paths = [str(s.path) for s in stores]
        jobs = [task(paths, grid, tile, config, arrays, dask_key_name=f"world-tile-{'-'.join(map(str, tile.window.lo))}")
                for tile in fused]
        results = compute_tasks(jobs, client, desc="fuse-world", unit="tile", progress=progress)
    peaks: dict[int, int] = {}
    for pid, peak in results:
        peaks[pid] = max(peaks.get(pid, 0), peak)
    return WorldSummary(target, grid.shape, grid.origin, grid.voxel_size, len(tiles), len(fused),
                        sum(len(s) for s in stores), max(len(peaks), 1), max(peaks.values(), default=0),
                        time.perf_counter() - t0)


def _open_stores(workspaces: Sequence[str | Path]) -> list[FramesStore]:
    if not workspaces:
        raise FusionError("no workspaces given; pass the workspaces whose frames.zarr make the world (mapkit ingest first)")
    return [open_frames_store(w) for w in workspaces]  # paths or fsspec URLs, as every command


def _world_frame(stores: list[FramesStore]) -> str:
    """The flights' common world frame; raises when they differ (their poses could not share a map)."""
    frames = {str(s.attrs.get("world_frame", "world")) for s in stores}
    if len(frames) != 1:
        raise FusionError(f"the flights have different world frames ({', '.join(sorted(frames))}); "
                          "fuse only flights whose poses are in one world frame")
    return frames.pop()


@contextmanager
def _client(scheduler: str | None, workers: int | None) -> Iterator[Client | None]:
    """None (this process) for one local worker, else a local cluster's or the scheduler's client."""
    if scheduler is None and (workers or 1) == 1:
        yield None
        return
    from mapkit._dask import dask_client

    with dask_client(scheduler, workers=workers) as (client, _):
        yield client


def _depth_bounds(stores: list[FramesStore], fuse: FuseConfig) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Bounds of the depth points (within max_depth) of up to 60 frames per flight, strided pixels."""
    lo, hi = np.full(3, np.inf), np.full(3, -np.inf)
    for store in stores:
        K = store.K
        for i in np.unique(np.linspace(0, len(store) - 1, min(_MAX_BOUND_FRAMES, len(store))).round().astype(int)):
            depth = np.asarray(store.depth[int(i)])[::4, ::4]
            v, u = np.nonzero(np.isfinite(depth) & (depth <= fuse.max_depth))
            if not len(v):
                continue
            z = depth[v, u]
            pts = np.stack([(4 * u - K[0, 2]) / K[0, 0] * z, (4 * v - K[1, 2]) / K[1, 1] * z, z], axis=1)
            T = store.T_world_camera[int(i)]
            world = pts @ T[:3, :3].T + T[:3, 3]
            lo, hi = np.minimum(lo, world.min(axis=0)), np.maximum(hi, world.max(axis=0))
    if not np.all(np.isfinite(lo)):
        raise FusionError(f"no depth within fuse.max_depth {fuse.max_depth} m in the sampled frames; raise fuse.max_depth "
                          "or set bounds")
    return lo, hi


def _plan_tiles(grid: Grid, stores: list[FramesStore], config: WorldConfig) -> list[_Tile]:
    """Tiles over the grid, each with the frames (per flight) whose camera is within reach of it."""
    fc = config.fuse
    # how far from its camera a frame can change a voxel: depth, the truncation band, a TSDF block
    # (Open3D touches whole blocks), the solid-behind-surface marks and one world voxel
    reach = (fc.max_depth + config.solid_depth + fc.trunc * fc.voxel + 2 * BLOCK_RESOLUTION * fc.voxel
             + 2 * grid.voxel_size)
    cameras = [np.asarray(s.T_world_camera[:, :3, 3]) for s in stores]
    tiles = []
    for corner in np.ndindex(*(math.ceil(n / config.tile) for n in grid.shape)):
        lo = tuple(c * config.tile for c in corner)
        hi = tuple(min(a + config.tile, n) for a, n in zip(lo, grid.shape, strict=True))
        window = Window((lo[0], lo[1], lo[2]), (hi[0], hi[1], hi[2]))
        box_lo = grid.origin + grid.voxel_size * (np.asarray(lo) - 0.5)
        box_hi = grid.origin + grid.voxel_size * (np.asarray(hi) - 0.5)
        frames = []
        for cam in cameras:
            gap = np.linalg.norm(np.maximum(np.maximum(box_lo - cam, cam - box_hi), 0.0), axis=1)
            frames.append(tuple(int(i) for i in np.flatnonzero(gap <= reach)))
        tiles.append(_Tile(window, tuple(frames)))
    return tiles


@contextmanager
def _world_store(target: Path, grid: Grid, frame_id: str, config: WorldConfig, stores: list[FramesStore], *,
                 overwrite: bool) -> Iterator[dict[str, Any]]:
    """The world.zarr arrays to fill, under a temporary name; published (consolidated, renamed) on success."""
    import zarr
    from zarr.codecs import BloscCodec

    with atomic_output(target, overwrite=overwrite) as tmp:
        root = zarr.open_group(tmp, mode="w-", zarr_format=3)
        chunks = tuple(min(CHUNK, n) for n in grid.shape)
        arrays = {}
        for name, dtype, fill in (("tsdf", "float32", float("nan")), ("observed", "bool", False), ("behind", "bool", False)):
            arrays[name] = root.create_array(name, shape=grid.shape, chunks=chunks, dtype=dtype, fill_value=fill,
                                             compressors=[BloscCodec(cname="zstd", clevel=3, shuffle="shuffle")],
                                             dimension_names=["x", "y", "z"])
        root.attrs.update({
            "kind": KIND, "mapkit_version": __version__, "origin": [float(v) for v in grid.origin],
            "voxel_size": grid.voxel_size, "shape": list(grid.shape), "frame_id": frame_id, "fuse": asdict(config.fuse),
            "solid_depth": config.solid_depth, "tile": config.tile, "padding": config.padding,
            "sources": [str(s.path) for s in stores],
        })
        yield arrays
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # consolidated metadata is not (yet) in the v3 spec
            zarr.consolidate_metadata(tmp, zarr_format=3)


def _tile_task(paths: list[str], grid: Grid, tile: _Tile, config: WorldConfig, arrays: dict[str, Any]) -> tuple[int, int]:
    """Fuse, sample and carve one tile and write it; (process id, its peak RSS in bytes)."""
    stores = [open_frames_store(p) for p in paths]
    window = tile.window
    vbg = _tile_tsdf(stores, grid, tile, config.fuse)
    fc = config.fuse
    tsdf_m = sample_tsdf(vbg, grid, tsdf_voxel=fc.voxel, trunc_voxels=fc.trunc, window=window)
    del vbg
    seen = ~np.isnan(tsdf_m)
    observed = seen.copy()
    behind = np.zeros(window.shape, dtype=bool)
    for store, frames in zip(stores, tile.frames, strict=True):
        if frames:
            carve_free_space(store, grid, observed, max_depth=fc.max_depth, behind=behind, solid_depth=config.solid_depth,
                             window=window, frames=set(frames))
    observed &= ~((tsdf_m < 0) & ~seen)  # as mapkit esdf: a ray cannot clear what the TSDF calls inside
    arrays["tsdf"][window.slices] = tsdf_m
    arrays["observed"][window.slices] = observed
    arrays["behind"][window.slices] = behind
    return os.getpid(), resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024


def _tile_tsdf(stores: list[FramesStore], grid: Grid, tile: _Tile, fc: FuseConfig) -> Any:
    """A VoxelBlockGrid holding only the TSDF blocks around `tile`, every reaching frame integrated in order."""
    import open3d.core as o3c

    block = BLOCK_RESOLUTION * fc.voxel
    margin = fc.voxel  # samples within half a TSDF voxel of a centre count (occupancy_from_tsdf)
    box_lo = grid.origin + grid.voxel_size * np.asarray(tile.window.lo) - margin
    box_hi = grid.origin + grid.voxel_size * (np.asarray(tile.window.hi) - 1) + margin
    b_lo = np.floor(box_lo / block).astype(np.int64) - 1
    b_hi = np.floor(box_hi / block).astype(np.int64) + 1
    capacity = int(min(np.prod(b_hi - b_lo + 1), _MAX_TILE_BLOCKS))
    device = o3c.Device("CPU:0")
    vbg = _tsdf_grid(fc.voxel, block_count=capacity, device=device)
    for store, frames in zip(stores, tile.frames, strict=True):
        K = _o3d_intrinsics(store.K)
        for i in frames:
            if i % fc.stride:  # FuseConfig.stride: every stride-th frame
                continue
            raw = np.asarray(store.depth[i])
            if not np.any(raw <= fc.max_depth):  # as mapkit fuse: Open3D aborts on a frame that touches no block
                continue
            image = _o3d_depth(_o3d_ready(raw), device)
            extrinsic = _o3c_tensor(invert_transform(store.T_world_camera[i]), o3c.float64)
            touched = _touched_blocks(vbg, image, K, extrinsic, fc)
            if touched is None:
                continue
            coords = touched.numpy()
            mine = np.all((coords >= b_lo) & (coords <= b_hi), axis=1)
            if not mine.any():
                continue
            mine_coords = _o3c_tensor(np.ascontiguousarray(coords[mine]), touched.dtype)
            vbg.integrate(mine_coords, image, K, extrinsic, 1.0, float(fc.max_depth), float(fc.trunc))
    return vbg


def open_world(directory: str | Path) -> Any:
    """The zarr group of ``directory/world.zarr``; raises when there is none or it is not a world."""
    import zarr

    path = Path(directory) / WORLD
    if not path.exists():
        raise FusionError(f"{path} does not exist; run `mapkit fuse-world WS... -o {directory}` first")
    try:
        root = zarr.open_group(path, mode="r")
    except Exception as exc:  # noqa: BLE001 - zarr raises several types for a damaged store: one message
        raise FusionError(f"{path} is not a readable world ({exc}); re-run `mapkit fuse-world --overwrite`") from None
    if root.attrs.get("kind") != KIND:
        raise FusionError(f"{path} is not a mapkit world (kind {root.attrs.get('kind')!r}); re-run `mapkit fuse-world`")
    return root
