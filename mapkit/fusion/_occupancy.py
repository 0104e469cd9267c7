"""From a fused TSDF and the frames that made it to a dense occupancy + observed grid for the ESDF."""

from __future__ import annotations

from collections.abc import Collection
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from mapkit.fusion._tsdf import FusionError
from mapkit.ingest import FramesStore

_BLOCKS_PER_BATCH = 2048  # TSDF blocks read at a time: bounds memory on large maps
_MIN_WEIGHT = 1.0  # integration weight a TSDF sample needs to count


@dataclass
class Grid:
    """A regular grid: voxel [i, j, k] has centre origin + voxel_size * (i, j, k)."""

    origin: NDArray[np.float64]
    voxel_size: float
    shape: tuple[int, int, int]

    @classmethod
    def covering(cls, lo: NDArray[np.float64], hi: NDArray[np.float64], voxel_size: float) -> Grid:
        """The grid whose voxel centres cover [lo, hi]; centres on multiples of voxel_size so that a
        TSDF voxel size dividing voxel_size puts TSDF samples exactly on ESDF centres."""
        origin = np.floor(np.asarray(lo, float) / voxel_size) * voxel_size
        shape = np.ceil((np.asarray(hi, float) - origin) / voxel_size - 1e-9).astype(int) + 1
        return cls(origin, float(voxel_size), (int(shape[0]), int(shape[1]), int(shape[2])))

    @property
    def size(self) -> int:
        return int(np.prod(self.shape))


@dataclass(frozen=True)
class Window:
    """A box of voxels [lo, hi) of a :class:`Grid` (a tile): arrays over it are indexed from `lo`."""

    lo: tuple[int, int, int]
    """First voxel index on each axis."""
    hi: tuple[int, int, int]
    """One past the last voxel index on each axis."""

    @classmethod
    def whole(cls, grid: Grid) -> Window:
        return cls((0, 0, 0), grid.shape)

    @property
    def shape(self) -> tuple[int, int, int]:
        return (self.hi[0] - self.lo[0], self.hi[1] - self.lo[1], self.hi[2] - self.lo[2])

    @property
    def slices(self) -> tuple[slice, slice, slice]:
        return (slice(self.lo[0], self.hi[0]), slice(self.lo[1], self.hi[1]), slice(self.lo[2], self.hi[2]))


def _tsdf_samples(vbg: Any, batch: int = _BLOCKS_PER_BATCH):
    """(positions (N,3), tsdf (N,), weight (N,)) of every voxel of a VoxelBlockGrid, in block batches."""
    import open3d.core as o3c

    active = vbg.hashmap().active_buf_indices()
    tsdf_all = vbg.attribute("tsdf").reshape((-1,))
    weight_all = vbg.attribute("weight").reshape((-1,))
    n = active.shape[0]
    for start in range(0, n, batch):
        buf = active[start : start + batch].to(o3c.int32)
        coords, flat = vbg.voxel_coordinates_and_flattened_indices(buf)
        flat = flat.reshape((-1,))
        yield coords.numpy().astype(np.float64), tsdf_all[flat].numpy(), weight_all[flat].numpy()


def occupancy_from_tsdf(
    tsdf_path: Path, grid: Grid, *, tsdf_voxel: float, trunc_voxels: float
) -> tuple[NDArray[np.bool_], NDArray[np.float32]]:
    """(occupied, tsdf) on `grid` from the TSDF sample nearest each voxel centre: tsdf in metres, NaN
    where no sample has weight >= 1; occupied = tsdf < 0 (centre sampling keeps boundaries unbiased)."""
    import open3d as o3d

    if not tsdf_path.exists():
        raise FusionError(f"{tsdf_path} does not exist; run `mapkit fuse` first")
    try:
        vbg = o3d.t.geometry.VoxelBlockGrid.load(str(tsdf_path))
    except Exception as exc:  # noqa: BLE001 - Open3D raises RuntimeError or others for a bad file: one message
        raise FusionError(f"{tsdf_path} is not a readable TSDF ({exc}); re-run `mapkit fuse --overwrite`") from None
    tsdf_m = sample_tsdf(vbg, grid, tsdf_voxel=tsdf_voxel, trunc_voxels=trunc_voxels)
    return tsdf_m < 0, tsdf_m


def sample_tsdf(vbg: Any, grid: Grid, *, tsdf_voxel: float, trunc_voxels: float,
                window: Window | None = None) -> NDArray[np.float32]:
    """The TSDF (metres, NaN = no sample) at the centres of `window`'s voxels of `grid` (default: all),
    bit for bit the whole grid's values there."""
    window = window or Window.whole(grid)
    tsdf_m = np.full(window.shape, np.nan, dtype=np.float32)
    half = 0.5 * tsdf_voxel + 1e-6
    lo, hi = np.asarray(window.lo), np.asarray(window.hi)
    trunc_m = trunc_voxels * tsdf_voxel
    for pos, tsdf, weight in _tsdf_samples(vbg):
        keep = weight >= _MIN_WEIGHT
        pos, tsdf = pos[keep], tsdf[keep]
        rel = (pos - grid.origin) / grid.voxel_size
        idx = np.rint(rel).astype(np.int64)
        near = np.all(np.abs(rel - idx) * grid.voxel_size < half, axis=1)
        inside = np.all((idx >= lo) & (idx < hi), axis=1)
        sel = near & inside
        i, j, k = (idx[sel] - lo).T
        tsdf_m[i, j, k] = tsdf[sel] * trunc_m
    return tsdf_m


def carve_free_space(
    store: FramesStore, grid: Grid, observed: NDArray[np.bool_], *, max_depth: float,
    behind: NDArray[np.bool_] | None = None, solid_depth: float = 0.0,
    max_frames: int = 120, progress: bool = False, window: Window | None = None,
    frames: Collection[int] | None = None,
) -> int:
    """Mark voxels that depth rays passed through as observed (in place); returns the frames used.

    At most `max_frames` frames, rays about one voxel apart at the far range, sampled every 0.8 voxel
    up to the surface. With `behind`, voxels up to `solid_depth` beyond each surface are marked there.
    `observed` and `behind` cover `window` of `grid` (default: all), with exactly the whole grid's
    marks there; `frames`: only these of the subsampled frames.
    """
    from tqdm import tqdm

    K = store.K
    n = len(store)
    frame_step = max(1, int(np.ceil(n / max_frames)))
    pix_step = max(1, int(np.floor(grid.voxel_size * min(K[0, 0], K[1, 1]) / max_depth)))
    rays = _pixel_rays(K, store.height, store.width, pix_step)
    marker = _RayMarker.on(grid, window or Window.whole(grid), step=0.8 * grid.voxel_size)
    step = marker.step
    flat = observed.reshape(-1)
    used = 0

    focal = 0.5 * (K[0, 0] + K[1, 1]) / pix_step  # focal length in strided pixels
    chosen = [i for i in range(0, n, frame_step) if frames is None or i in frames]
    for i in tqdm(chosen, desc="observed", unit="frame", disable=not progress):
        image = np.asarray(store.depth[i])[::pix_step, ::pix_step]
        depth = image.reshape(-1)
        ok = np.isfinite(depth)
        z_end = np.minimum(depth[ok], max_depth) - step
        if not len(z_end):
            continue
        T = store.T_world_camera[i]
        dirs = rays[ok] @ T[:3, :3].T  # world-frame ray per unit optical depth
        counts = np.maximum((z_end / step).astype(np.int64), 0)
        marker.mark(flat, T[:3, 3], dirs, np.zeros_like(z_end), counts)
        if behind is not None and solid_depth > 0:
            # Go deeper behind surfaces seen head-on than behind grazing ones (cos of the view angle
            # from the depth gradient): a grazing ray leaves a thin object within centimetres.
            gv, gu = np.gradient(image)
            tan = np.hypot(gu, gv).reshape(-1)[ok] * focal / depth[ok]
            cos = 1.0 / np.sqrt(1.0 + np.nan_to_num(tan, nan=1e6) ** 2)
            hit = depth[ok] <= max_depth
            n_behind = np.floor(solid_depth * cos[hit] / step).astype(np.int64)
            marker.mark(behind.reshape(-1), T[:3, 3], dirs[hit], depth[ok][hit] + step, n_behind)
        used += 1
    return used


def _pixel_rays(K: NDArray[np.float64], H: int, W: int, pix_step: int) -> NDArray[np.float64]:
    """(N, 3) optical-frame ray per unit optical depth through every `pix_step`-th pixel (row-major)."""
    v, u = np.mgrid[0:H:pix_step, 0:W:pix_step]
    return np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones_like(u, dtype=float)], -1).reshape(-1, 3)


@dataclass(frozen=True)
class _RayMarker:
    """Sets the voxels of a window of a grid that samples along rays land in (:func:`carve_free_space`)."""

    grid: Grid
    step: float
    """Metres of optical depth between samples."""
    lo: NDArray[np.int64]
    hi: NDArray[np.int64]
    strides: NDArray[np.int64]
    """Of the window's flattened array."""
    tile: bool
    """The window is part of the grid: only samples that can land in it are computed."""

    @classmethod
    def on(cls, grid: Grid, window: Window, *, step: float) -> _RayMarker:
        strides = np.array([window.shape[1] * window.shape[2], window.shape[2], 1])
        return cls(grid, step, np.asarray(window.lo), np.asarray(window.hi), strides, window != Window.whole(grid))

    def mark(self, target: NDArray[np.bool_], origin: NDArray[np.float64], dirs: NDArray[np.float64],
             z0: NDArray[np.float64], counts: NDArray[np.int64]) -> None:
        """Set the voxels at optical depths z0 + (n + 0.5) * step, n < counts, along each ray."""
        grid, step, lo, hi = self.grid, self.step, self.lo, self.hi
        start = np.cumsum(counts) - counts
        # Voxel coordinates directly (float32 halves the memory traffic of this hot loop).
        scaled_dirs = (dirs / grid.voxel_size).astype(np.float32)
        base = ((origin - grid.origin) / grid.voxel_size).astype(np.float32)
        if self.tile:  # only the samples that can land in the window, each computed as for the whole grid
            first, stop = _samples_in_box(base, scaled_dirs, z0, counts, step, lo.astype(np.float64) - 1.0,
                                          hi.astype(np.float64))
            kept = stop - first
            ray_id = np.repeat(np.arange(len(kept)), kept)
            # sample n of a ray is element start + n of the whole grid's enumeration (float32 there too)
            element = np.repeat(start + first - (np.cumsum(kept) - kept), kept) + np.arange(kept.sum())
            offset = element.astype(np.float32) - np.repeat(start, kept).astype(np.float32)
            z = np.repeat(z0.astype(np.float32), kept) + (offset + 0.5) * np.float32(step)
        else:
            ray_id = np.repeat(np.arange(len(counts)), counts)
            z = np.repeat(z0.astype(np.float32), counts) + (
                np.arange(counts.sum(), dtype=np.float32) - np.repeat(start, counts).astype(np.float32) + 0.5
            ) * np.float32(step)
        idx = np.rint(base + scaled_dirs[ray_id] * z[:, None]).astype(np.int64)
        inside = np.all((idx >= lo) & (idx < hi), axis=1)
        target[(idx[inside] - lo) @ self.strides] = True


def _samples_in_box(base: NDArray[np.float32], dirs: NDArray[np.float32], z0: NDArray[np.float64],
                    counts: NDArray[np.int64], step: float, box_lo: NDArray[np.float64],
                    box_hi: NDArray[np.float64]) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
    """Per ray, the sample range [first, stop) of n < counts whose position base + dirs * (z0 + (n + 0.5)
    * step) (voxel coordinates) can lie in [box_lo, box_hi]: the slab intersection, widened by two
    samples each side so float32 rounding of the positions cannot drop one."""
    d = dirs.astype(np.float64)
    b = base.astype(np.float64)
    with np.errstate(divide="ignore", invalid="ignore"):
        t1, t2 = (box_lo - b) / d, (box_hi - b) / d
    parallel = d == 0
    inside_slab = (b >= box_lo) & (b <= box_hi)
    enter = np.where(parallel, np.where(inside_slab, -np.inf, np.inf), np.minimum(t1, t2)).max(axis=1)
    leave = np.where(parallel, np.where(inside_slab, np.inf, -np.inf), np.maximum(t1, t2)).min(axis=1)
    with np.errstate(invalid="ignore"):
        n_lo = np.floor(np.clip((enter - z0) / step - 0.5, -2.0, counts + 2.0)) - 2
        n_hi = np.ceil(np.clip((leave - z0) / step - 0.5, -2.0, counts + 2.0)) + 3
    first = np.clip(n_lo, 0, counts).astype(np.int64)
    stop = np.clip(n_hi, 0, counts).astype(np.int64)
    empty = ~(leave >= enter)
    stop[empty] = first[empty]
    return first, np.maximum(stop, first)


def fill_unknown(
    occupied: NDArray[np.bool_], observed: NDArray[np.bool_], policy: str, *, behind: NDArray[np.bool_] | None = None
) -> NDArray[np.bool_]:
    """The obstacle mask under the unknown-space policy: "occupied" makes every unobserved voxel an
    obstacle; "free" frees them except `behind` ones and pockets no observed free voxel reaches."""
    if policy == "occupied":
        return occupied | ~observed
    if policy != "free":
        raise FusionError(f"unknown {policy!r}: expected occupied or free")
    from scipy import ndimage

    solid = occupied | (behind & ~observed) if behind is not None else occupied.copy()
    labels, count = ndimage.label(~solid)
    if count == 0:
        return solid
    reached = np.zeros(count + 1, dtype=bool)
    reached[np.unique(labels[observed & ~solid])] = True
    reached[0] = True  # label 0: the obstacles themselves
    return ~reached[labels] | solid
