"""TSDF fusion of frames.zarr with Open3D's tensor VoxelBlockGrid → cloud.ply / mesh.ply / tsdf.npz."""

from __future__ import annotations

import json
import logging
import os
import time
from collections.abc import Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import NDArray

from mapkit import _staging
from mapkit._resources import available_memory
from mapkit._threads import prefetch
from mapkit._version import __version__
from mapkit.errors import MapkitError
from mapkit.geometry import invert_transform
from mapkit.ingest import FramesStore, IngestConfig, ingest, open_frames_store
from mapkit.workspace import FRAMES, atomic_output, check_writable, clean_stale

if TYPE_CHECKING:
    import open3d as o3d
    import open3d.core as o3c

log = logging.getLogger(__name__)

BLOCK_RESOLUTION = 8  # voxels per block edge: measured ~1.5x faster integration than 16 (fewer voxels outside the truncation band)
_BYTES_PER_VOXEL = 8  # tsdf + weight, float32 each
CLOUD, MESH, TSDF = "cloud.ply", "mesh.ply", "tsdf.npz"
FUSE_META = "fuse.json"
"""Written last by fuse: the config, bounds and the outputs' sizes (see :func:`check_fused`)."""


class FusionError(MapkitError):
    """Fusion cannot run with these inputs or options."""


@dataclass
class FuseConfig:
    """TSDF fusion options: each field is a setting of `mapkit fuse` (`mapkit config fuse`)."""

    voxel: float = 0.05
    """TSDF voxel size in metres."""
    trunc: float = 4.0
    """Truncation distance in voxels (Open3D's trunc_voxel_multiplier)."""
    max_depth: float = 8.0
    """Depth beyond this (metres) is not integrated."""
    device: str = "cpu"
    """'cpu' or 'cuda:N'."""
    weight_threshold: float = 2.0
    """Minimum integration weight for a surface point to be extracted."""
    stride: int = 1
    """Integrate every stride-th frame of frames.zarr."""
    mesh: bool = False
    """Also extract a marching-cubes mesh."""

    def validate(self) -> None:
        if not self.voxel > 0:
            raise FusionError(f"--voxel {self.voxel} must be positive (metres, e.g. 0.05)")
        if not self.trunc >= 1:
            raise FusionError(f"trunc {self.trunc} must be at least 1 voxel (e.g. 4)")
        if not self.max_depth > 0:
            raise FusionError(f"max_depth {self.max_depth} must be positive (metres)")
        if self.stride < 1:
            raise FusionError(f"stride {self.stride} must be at least 1")


@dataclass
class FuseSummary:
    """What fusion did."""

    frames_used: int
    frames_total: int
    dropped: dict[str, int]
    blocks: int
    voxels: int
    points: int
    bounds: NDArray[np.float64]
    seconds: float
    integrate_seconds: float
    outputs: list[Path] = field(default_factory=list)
    """Every file and store written, in order: frames.zarr when this call ingested it, cloud.ply,
    tsdf.npz, mesh.ply (``mesh``), fuse.json; for a workspace at a URL, the local copies they were
    published from (``urls`` names them where they now are)."""
    urls: list[str] = field(default_factory=list)
    """For a workspace at a URL: where each of ``outputs`` was published."""

    @property
    def frames_per_second(self) -> float:
        return self.frames_used / self.seconds if self.seconds > 0 else float("inf")

    @property
    def integrate_frames_per_second(self) -> float:
        return self.frames_used / self.integrate_seconds if self.integrate_seconds > 0 else float("inf")


def _device(name: str) -> Any:
    import open3d.core as o3c

    text = name.strip().lower()
    if text == "cpu":
        return o3c.Device("CPU:0")
    if text.startswith("cuda"):
        index = int(text.split(":")[1]) if ":" in text else 0
        if not o3c.cuda.is_available() or index >= o3c.cuda.device_count():
            raise FusionError(
                f"--device {name}: Open3D sees {o3c.cuda.device_count()} CUDA device(s), not device {index}; "
                "use --device cpu (or a machine with a GPU and Open3D's CUDA build)"
            )
        return o3c.Device(f"CUDA:{index}")
    raise FusionError(f"--device {name!r}: expected cpu or cuda:N")


def _o3c_tensor(array: NDArray[Any], dtype: o3c.Dtype) -> o3c.Tensor:
    """A copy of `array` as an Open3D tensor of `dtype` on the CPU."""
    import open3d.core as o3c

    return o3c.Tensor(array, dtype, o3c.Device("CPU:0"))


def _tsdf_grid(voxel: float, *, block_count: int, device: o3c.Device) -> o3d.t.geometry.VoxelBlockGrid:
    """An empty VoxelBlockGrid on `device` (float32 ``tsdf`` and ``weight``) with room for `block_count` blocks."""
    import open3d as o3d
    import open3d.core as o3c

    channels = (o3c.SizeVector([1]), o3c.SizeVector([1]))
    return o3d.t.geometry.VoxelBlockGrid(("tsdf", "weight"), (o3c.float32, o3c.float32), channels, voxel_size=voxel,
                                         block_resolution=BLOCK_RESOLUTION, block_count=block_count, device=device)


def _o3d_ready(depth: NDArray[np.float32]) -> NDArray[np.float32]:
    """Native-endian float32 (Open3D rejects zarr's explicit '<f4') with invalid pixels as 0."""
    native = np.empty(np.shape(depth), dtype=np.float32)
    np.copyto(native, depth)
    native[np.isnan(native)] = 0.0
    return native


def _o3d_depth(depth: NDArray[np.float32], device: Any) -> Any:
    """Open3D image of a depth frame made ready by `_o3d_ready`."""
    import open3d as o3d
    import open3d.core as o3c

    return o3d.t.geometry.Image(_o3c_tensor(depth, o3c.float32)).to(device)


def _o3d_intrinsics(K: NDArray[np.float64]) -> Any:
    """K with the principal point shifted by half a pixel: Open3D floors a voxel's projection while
    mapkit puts integer pixels at pixel centres (unshifted, a grazing floor fuses 0.33 voxel low)."""
    import open3d.core as o3c

    K = np.array(K, dtype=np.float64)
    K[0, 2] += 0.5
    K[1, 2] += 0.5
    return _o3c_tensor(K, o3c.float64)


def _touched_blocks(vbg: Any, image: Any, K: Any, extrinsic: Any, config: FuseConfig) -> Any:
    """The blocks a depth image touches, or None when it touches none (Open3D raises then: an
    image of a few pixels, or depth only at its edges)."""
    try:
        return vbg.compute_unique_block_coordinates(image, K, extrinsic, 1.0, float(config.max_depth), float(config.trunc))
    except RuntimeError as exc:
        if "No block is touched" in str(exc):
            return None
        raise


def estimate_blocks(store: FramesStore, config: FuseConfig, *, sample: int = 24) -> int:
    """Blocks the map will need: the union of the blocks `sample` evenly spaced frames touch, scaled
    to the whole flight by the share of new blocks the later samples still add."""
    import open3d.core as o3c

    n = len(store)
    idx = np.unique(np.linspace(0, n - 1, min(sample, n)).round().astype(int))
    probe = _tsdf_grid(config.voxel, block_count=1000, device=o3c.Device("CPU:0"))
    K = _o3d_intrinsics(store.K)
    seen = np.empty(0, dtype=np.int64)
    growth = []
    for i in idx:
        depth = np.asarray(store.depth[int(i)])
        if not np.any(depth <= config.max_depth):
            continue
        touched = _touched_blocks(probe, _o3d_depth(_o3d_ready(depth), o3c.Device("CPU:0")), K,
                                  _o3c_tensor(invert_transform(store.T_world_camera[int(i)]), o3c.float64), config)
        if touched is None:
            continue
        coords = touched.numpy()
        c = coords.reshape(-1, 3).astype(np.int64) + (1 << 20)  # block keys packed into one int64
        keys = (c[:, 0] << 42) | (c[:, 1] << 21) | c[:, 2]
        before = len(seen)
        seen = np.union1d(seen, keys)
        growth.append(len(seen) - before)
    if not growth:
        return 256
    per_frame_new = np.mean(growth[len(growth) // 2 :])
    # Frames between samples add about as many new blocks as the later samples did per sample.
    unseen_frames = max(n - len(idx), 0) * len(idx) / max(n, 1)
    return int(len(seen) + per_frame_new * unseen_frames + 256)


def _surface_points(vbg: Any, config: FuseConfig) -> Any:
    """The TSDF's zero crossing as an Open3D point cloud, or None when it has none (Open3D raises on
    an empty extraction instead of returning an empty cloud)."""
    try:
        return vbg.extract_point_cloud(weight_threshold=config.weight_threshold)
    except RuntimeError as exc:
        if "has shape {0}" in str(exc):
            return None
        raise


def _written(path: Path, ok: bool, what: str, count: int, read: Any) -> None:
    """Raise unless Open3D reported success and ``path`` reads back with ``count`` elements: its
    writers return False, or write short files on a full disk, without raising."""
    import open3d as o3d

    if not ok or not path.exists() or path.stat().st_size == 0:
        complete = False
    else:
        with o3d.utility.VerbosityContextManager(o3d.utility.VerbosityLevel.Error):  # a short file warns
            complete = read(path) == count
    if not complete:
        raise FusionError(f"could not write the {what} completely to {path.parent} (disk full or not writable?); "
                          "the previous outputs were kept")


def _write_outputs(workspace: Path, cloud: Any, vbg: Any, config: FuseConfig, meta: dict[str, Any]) -> None:
    """cloud.ply, tsdf.npz (+ mesh.ply), then fuse.json with their sizes, as one unit: each file is
    staged and checked first, and fuse.json is removed before the first replacement."""
    import open3d as o3d

    workspace.mkdir(parents=True, exist_ok=True)
    clean_stale(workspace)
    tag = f".partial-{os.getpid()}"
    staged: dict[str, Path] = {}
    try:
        staged[CLOUD] = workspace / f".{CLOUD}{tag}.ply"
        legacy = cloud.to_legacy()
        _written(staged[CLOUD], o3d.io.write_point_cloud(staged[CLOUD], legacy, write_ascii=False), "cloud",
                 len(legacy.points), lambda p: len(o3d.io.read_point_cloud(p).points))
        if config.mesh:
            staged[MESH] = workspace / f".{MESH}{tag}.ply"
            mesh = vbg.extract_triangle_mesh(weight_threshold=config.weight_threshold).cpu().to_legacy()
            mesh.compute_vertex_normals()
            _written(staged[MESH], o3d.io.write_triangle_mesh(staged[MESH], mesh, write_ascii=False), "mesh",
                     len(mesh.triangles), lambda p: len(o3d.io.read_triangle_mesh(p).triangles))
        staged[TSDF] = workspace / f".{TSDF}{tag}.npz"
        vbg.cpu().save(str(staged[TSDF]))
        _written(staged[TSDF], True, "TSDF", 1, lambda p: int(np.load(p).files != []))
    except BaseException:
        for path in staged.values():
            path.unlink(missing_ok=True)
        raise
    manifest = workspace / FUSE_META
    manifest.unlink(missing_ok=True)
    for name, path in staged.items():
        os.replace(path, workspace / name)
    meta["outputs"] = {name: (workspace / name).stat().st_size for name in staged}
    with atomic_output(manifest, overwrite=True) as tmp:
        tmp.write_text(json.dumps(meta, indent=2))


def check_fused(workspace: Path) -> dict[str, Any]:
    """fuse.json of ``workspace``, after checking that the outputs it lists are the ones it describes
    (a fuse killed while replacing them leaves no fuse.json, or files of another size)."""
    manifest = workspace / FUSE_META
    if not (workspace / TSDF).exists() or not manifest.exists():
        raise FusionError(f"{workspace} has no complete fused map (tsdf.npz, fuse.json); run `mapkit fuse BAG... "
                          f"-w {workspace}` (with --overwrite when a fuse was interrupted)")
    try:
        meta = json.loads(manifest.read_text())
    except (OSError, ValueError) as exc:
        raise FusionError(f"{manifest} is unreadable ({exc}); re-run `mapkit fuse --overwrite`") from None
    for name, size in meta.get("outputs", {}).items():  # older workspaces have no sizes
        path = workspace / name
        if not path.exists() or path.stat().st_size != size:
            raise FusionError(f"{path} is not the file fuse.json describes (a fuse was interrupted or the file was "
                              f"changed); re-run `mapkit fuse --overwrite -w {workspace}`")
    return meta


def fuse_store(store: FramesStore, workspace: Path, config: FuseConfig, *, overwrite: bool = False, progress: bool = True) -> FuseSummary:
    """Integrate every frame of `store` into a TSDF; write cloud.ply (+ mesh.ply) and tsdf.npz."""
    config.validate()
    outputs = [workspace / CLOUD, workspace / TSDF] + ([workspace / MESH] if config.mesh else [])
    for path in outputs:
        check_writable(path, overwrite=overwrite)
    if len(store) == 0:
        raise FusionError(f"{store.path} has no frames (dropped: {store.attrs.get('dropped')}); nothing to fuse")
    device = _device(config.device)
    t0 = time.perf_counter()
    vbg = _voxel_grid(store, config, device)
    indices = range(0, len(store), config.stride)
    skipped, integrate_s = _integrate(vbg, store, indices, config, device, progress=progress)
    cloud, n_points = _extract_cloud(vbg, config, len(indices))
    positions = cloud.point.positions.numpy()
    bounds = np.stack([positions.min(axis=0), positions.max(axis=0)]).astype(np.float64)
    meta = {
        "mapkit_version": __version__,
        "frames": str(store.path),
        "config": asdict(config),
        "world_frame": store.attrs.get("world_frame"),
        "points": n_points,
        "bounds": bounds.tolist(),
    }
    _write_outputs(workspace, cloud, vbg, config, meta)
    active = int(vbg.hashmap().size())
    return FuseSummary(
        frames_used=len(indices) - skipped, frames_total=len(store), dropped=dict(store.attrs.get("dropped", {})),
        blocks=active, voxels=active * BLOCK_RESOLUTION**3, points=n_points, bounds=bounds,
        seconds=time.perf_counter() - t0, integrate_seconds=integrate_s, outputs=[*outputs, workspace / FUSE_META],
    )


def _voxel_grid(store: FramesStore, config: FuseConfig, device: Any) -> Any:
    """An empty VoxelBlockGrid sized for the surface the frames see; raises when it would not fit in memory."""
    blocks = estimate_blocks(store, config)
    block_bytes = BLOCK_RESOLUTION**3 * _BYTES_PER_VOXEL * 2  # hash map keeps ~2x headroom
    need = blocks * block_bytes
    have = available_memory()
    if need > 0.8 * have:
        fits = config.voxel * (need / (0.6 * have)) ** 0.5  # surface blocks scale ~ 1/voxel²
        raise FusionError(
            f"the TSDF at --voxel {config.voxel} needs about {need / 2**30:.1f} GiB ({blocks} blocks) but "
            f"{have / 2**30:.1f} GiB is available; use --voxel {fits:.3f} or larger"
        )
    return _tsdf_grid(config.voxel, block_count=blocks, device=device)


def _depth_batches(store: FramesStore, indices: range, config: FuseConfig, size: int = 16) -> Any:
    """(frame indices, [(Open3D-ready depth, any depth within max_depth)]) for batches of ``size`` frames."""
    for start in range(0, len(indices), size):
        chunk = list(indices[start : start + size])
        block = store.depth[chunk[0] : chunk[-1] + 1 : config.stride]
        yield chunk, [(_o3d_ready(d), bool(np.any(d <= config.max_depth))) for d in block]


def _integrate(vbg: Any, store: FramesStore, indices: range, config: FuseConfig, device: Any, *,
               progress: bool) -> tuple[int, float]:
    """Integrate the frames at ``indices`` into ``vbg`` → (frames skipped, seconds integrating); raises
    when no frame touches the map."""
    import open3d.core as o3c
    from tqdm import tqdm

    K = _o3d_intrinsics(store.K)
    integrate_s = 0.0
    skipped = 0
    bar = tqdm(total=len(indices), unit="frame", desc="fuse", disable=not progress, dynamic_ncols=True)
    # zarr decompression and conversion in a second thread overlap Open3D's integration.
    for chunk, depths in prefetch(_depth_batches(store, indices, config), depth=2):
        for i, (depth, in_range) in zip(chunk, depths, strict=True):
            bar.update(1)
            if not in_range:  # Open3D aborts on a frame that touches no block
                skipped += 1
                continue
            t = time.perf_counter()
            image = _o3d_depth(depth, device)
            extrinsic = _o3c_tensor(invert_transform(store.T_world_camera[i]), o3c.float64)
            coords = _touched_blocks(vbg, image, K, extrinsic, config)
            if coords is None:
                skipped += 1
                continue
            vbg.integrate(coords, image, K, extrinsic, 1.0, float(config.max_depth), float(config.trunc))
            integrate_s += time.perf_counter() - t
    bar.close()
    if skipped == len(indices):
        raise FusionError(
            f"no frame touches the map: depth within max_depth {config.max_depth} m is needed (nearest valid "
            f"depth in the first frame: {np.nanmin(store.depth[0]):.2f} m) on images of more than a few pixels "
            f"(these are {store.depth.shape[2]}x{store.depth.shape[1]}); raise max_depth (--set max_depth=M) or check the depth topic"
        )
    return skipped, integrate_s


def _extract_cloud(vbg: Any, config: FuseConfig, n_frames: int) -> tuple[Any, int]:
    """(surface point cloud on the CPU, its point count); raises when no voxel saw a surface often enough."""
    pcd = _surface_points(vbg, config)
    n_points = int(pcd.point.positions.shape[0]) if pcd is not None and "positions" in pcd.point else 0
    if n_points == 0:
        raise FusionError(
            f"fusion produced an empty cloud from {n_frames} frames (--voxel {config.voxel} m, max_depth "
            f"{config.max_depth} m, weight threshold {config.weight_threshold}): no voxel saw a surface often enough; "
            f"use a voxel near the depth's resolution (e.g. --voxel 0.05) and check max_depth and the frames' depth"
        )
    return pcd.cpu(), n_points


def fuse(
    recordings: Sequence[str | Path],
    workspace: str | Path,
    config: FuseConfig | None = None,
    ingest_config: IngestConfig | None = None,
    *,
    overwrite: bool = False,
    progress: bool = True,
) -> FuseSummary:
    """Ingest `recordings` (reusing an up-to-date frames.zarr) and fuse them (see `fuse_store`).

    `workspace` may be an fsspec URL: the work then runs in a local temporary folder and frames.zarr
    (when ingested here) and the fused files are published at the URL (:mod:`mapkit._staging`)."""
    config = config or FuseConfig()
    config.validate()
    _device(config.device)  # before ingesting: a missing GPU should not cost an ingest first
    ingest_config = ingest_config or IngestConfig()
    url = _staging.remote(workspace)
    if url is not None:
        return _fuse_at_url(recordings, url, config, ingest_config, overwrite=overwrite, progress=progress)
    workspace = Path(workspace)
    frames_path = workspace / FRAMES
    ingested = False
    if recordings:
        current = False
        if frames_path.exists():
            try:
                current = open_frames_store(workspace).is_current(recordings, ingest_config)
            except MapkitError:
                current = False
        if not current:
            ingest(recordings, workspace, ingest_config, overwrite=overwrite or not frames_path.exists(), progress=progress)
            ingested = True
        else:
            log.info("reusing up-to-date %s", frames_path)
    elif not frames_path.exists():
        raise FusionError(f"no recordings given and {frames_path} does not exist; pass BAG... or run `mapkit ingest` first")
    summary = fuse_store(open_frames_store(workspace), workspace, config, overwrite=overwrite, progress=progress)
    if ingested:  # the summary names every output of the call, the store it ingested too
        summary.outputs.insert(0, frames_path)
    return summary


def _fuse_at_url(recordings: Sequence[str | Path], url: str, config: FuseConfig, ingest_config: IngestConfig, *,
                 overwrite: bool, progress: bool) -> FuseSummary:
    """:func:`fuse` for a workspace at a URL: in a local temporary folder holding a copy of the URL's
    frames.zarr, then published (a new frames.zarr with its zarr.json last, the fused files before
    the fuse.json that lists them)."""
    import tempfile

    if not overwrite and _staging.read_bytes(url, FUSE_META) is not None:
        raise FusionError(f"{url}/{FUSE_META} exists (a fused map); pass --overwrite to replace it")
    frames_before = _staging.read_bytes(url, _staging.store_marker(FRAMES))
    if frames_before is None and not recordings:
        raise FusionError(f"no recordings given and {url}/{FRAMES} does not exist; pass BAG... or run "
                          f"`mapkit ingest BAG... -w {url}` first")
    with tempfile.TemporaryDirectory(prefix="mapkit-fuse-") as tmp:
        local = Path(tmp)
        if frames_before is not None:
            _staging.download_store(url, FRAMES, local)
        try:
            summary = fuse(recordings, local, config, ingest_config, overwrite=overwrite, progress=progress)
        except MapkitError as exc:  # name the workspace the user gave, not the temporary folder
            raise type(exc)(str(exc).replace(str(local), url)) from None
        if (local / _staging.store_marker(FRAMES)).read_bytes() != frames_before:
            _staging.publish_store(local, url, FRAMES)
        _staging.publish_file_set(local, url, FUSE_META)
    summary.urls = [f"{url}/{p.name}" for p in summary.outputs]
    return summary
