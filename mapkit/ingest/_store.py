"""frames.zarr: writing it from a FrameStream, and reading it back (contract in DESIGN.md)."""

from __future__ import annotations

import json
import time
from collections import deque
from collections.abc import Sequence
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from mapkit._stores import Location, StoreError, check_store_writable, publish_store
from mapkit._version import __version__
from mapkit._zarr import read_whole
from mapkit.ingest._errors import IngestError
from mapkit.ingest._reader import Frame, FrameStream, IngestConfig, open_frames
from mapkit.workspace import FRAMES

_BATCH = 16  # frames per zarr write: large enough to amortise zarr's per-call overhead


@dataclass
class IngestSummary:
    """What `ingest` wrote and dropped."""

    path: Path | str
    """frames.zarr: a local path, or the URL it was published at."""
    frames: int
    depth_messages: int
    dropped: dict[str, int]
    width: int
    height: int
    seconds: float
    sources: list[dict[str, Any]] = field(default_factory=list)
    warnings: list[str] = field(default_factory=list)

    @property
    def frames_per_second(self) -> float:
        return self.frames / self.seconds if self.seconds > 0 else float("inf")


def source_fingerprint(path: Path) -> dict[str, Any]:
    """Identity of an input recording (a file, or every file of a rosbag2 folder): its path, total bytes
    and latest mtime, so later stages can tell whether their outputs are current."""
    files = sorted(p for p in path.rglob("*") if p.is_file()) if path.is_dir() else [path]
    stats = [p.stat() for p in files]
    return {"path": str(path.resolve()), "bytes": sum(s.st_size for s in stats),
            "mtime_ns": max((s.st_mtime_ns for s in stats), default=0)}


def _compressor() -> Any:
    from zarr.codecs import BloscCodec

    # lz4 + bit shuffle at level 1: fastest on noisy millimetre depth; zstd saves little more, slower.
    return BloscCodec(cname="lz4", clevel=1, shuffle="bitshuffle")


class _DepthWriter:
    """The ``depth`` array of a new frames.zarr, filled in batches of :data:`_BATCH` frames by a
    background thread; sized for ``capacity`` frames, made on the first frame, trimmed at the end."""

    def __init__(self, root: Any, capacity: int) -> None:
        self.root, self.capacity = root, capacity
        self.array: Any = None
        self.height = self.width = 0
        self.count = 0  # frames added
        self.batch: list[NDArray[np.float32]] = []
        self.pool = ThreadPoolExecutor(max_workers=1, thread_name_prefix="mapkit-ingest-writer")
        self.writes: deque[Future[None]] = deque()

    def add(self, frame: Frame) -> None:
        """Queue one frame's depth; the first frame fixes the image size, a different size later raises."""
        if self.array is None:
            self.height, self.width = frame.depth.shape
            self.array = self.root.create_array(
                "depth", shape=(self.capacity, self.height, self.width), chunks=(1, self.height, self.width),
                dtype="float32", compressors=[_compressor()], fill_value=float("nan"),
                dimension_names=["frame", "v", "u"],
            )
        if frame.depth.shape != (self.height, self.width):
            raise IngestError(
                f"input {frame.source_index} has {frame.depth.shape[1]}x{frame.depth.shape[0]} depth but earlier "
                f"frames are {self.width}x{self.height}; ingest different cameras into separate workspaces"
            )
        self.batch.append(frame.depth)
        self.count += 1

    def _write(self, start: int, block: NDArray[np.float32]) -> None:
        self.array[start : start + len(block)] = block

    def flush(self) -> None:
        """Hand the batch to the writer thread (at most 4 waiting); raise what the thread failed with so far."""
        if self.batch:
            self.writes.append(self.pool.submit(self._write, self.count - len(self.batch), np.stack(self.batch)))
            self.batch.clear()
        while self.writes and (len(self.writes) > 4 or self.writes[0].done()):
            self.writes.popleft().result()

    def close(self) -> None:
        """Stop the writer thread: once it has written everything queued, or at once after a failure."""
        self.pool.shutdown(wait=True, cancel_futures=any(w.done() and w.exception() for w in self.writes))

    def finish(self) -> None:
        """Raise the writer thread's failure, if any; trim the array to the frames written."""
        while self.writes:
            self.writes.popleft().result()
        assert self.array is not None
        if self.count != self.capacity:
            self.array.resize((self.count, self.height, self.width))


@dataclass
class _FramePoses:
    """The small per-frame arrays of frames.zarr, gathered while the depth images stream."""

    stamp_ns: list[int] = field(default_factory=list)
    T_world_camera: list[NDArray[np.float64]] = field(default_factory=list)
    T_world_body: list[NDArray[np.float64]] = field(default_factory=list)
    source_index: list[int] = field(default_factory=list)

    def add(self, frame: Frame) -> None:
        """Keep one frame's stamp, poses and input index."""
        self.stamp_ns.append(frame.stamp_ns)
        self.T_world_camera.append(frame.T_world_camera)
        self.T_world_body.append(frame.T_world_body)
        self.source_index.append(frame.source_index)

    def write(self, root: Any) -> None:
        """Write them as labelled arrays ``stamp_ns``, ``T_world_camera``, ``T_world_body``, ``source_index``."""
        n = len(self.stamp_ns)

        def small(name: str, data: NDArray[Any], dims: list[str]) -> None:
            root.create_array(name, data=data, dimension_names=dims)

        small("stamp_ns", np.asarray(self.stamp_ns, dtype=np.int64), ["frame"])
        small("T_world_camera", np.asarray(self.T_world_camera, dtype=np.float64).reshape(n, 4, 4), ["frame", "row", "col"])
        small("T_world_body", np.asarray(self.T_world_body, dtype=np.float64).reshape(n, 4, 4), ["frame", "row", "col"])
        small("source_index", np.asarray(self.source_index, dtype=np.int32), ["frame"])


def write_frames(stream: FrameStream, store_path: Path | Location, *, progress: bool = True) -> IngestSummary:
    """Write every frame of `stream` into a new zarr v3 group at `store_path` (a local path or a
    :class:`~mapkit._stores.Location`; must not exist)."""
    import zarr

    t0 = time.perf_counter()
    capacity = max(stream.expected_frames, 1)
    loc = Location.of(store_path)
    root = zarr.open_group(loc.zarr_store(read_only=False), mode="w-", zarr_format=3)
    depth = _DepthWriter(root, capacity)
    poses = _stream_frames(stream, depth, progress=progress)
    depth.finish()
    poses.write(root)
    sources = _sources_attrs(stream)
    dropped = {k: int(v) for k, v in sorted(stream.dropped.items())}
    root.attrs.update(_frames_attrs(stream, depth.width, depth.height, sources, dropped))
    return IngestSummary(loc.local if loc.local is not None else loc.url, depth.count, stream.depth_messages, dropped,
                         int(depth.width), int(depth.height), time.perf_counter() - t0, sources, list(stream.warnings))


def _stream_frames(stream: FrameStream, depth: _DepthWriter, *, progress: bool) -> _FramePoses:
    """Read every frame of ``stream`` into ``depth`` (written behind) and the returned poses, with a
    progress bar over the depth messages."""
    from tqdm import tqdm

    poses = _FramePoses()
    total_messages = sum(p.summary.topics[p.depth.topic].count for p in stream.plans)
    bar = tqdm(total=total_messages, unit="msg", desc="ingest", disable=not progress, dynamic_ncols=True)
    try:
        for frame in stream:
            depth.add(frame)
            poses.add(frame)
            bar.update(stream.depth_messages - bar.n)
            if len(depth.batch) == _BATCH:
                depth.flush()
        depth.flush()
    finally:
        depth.close()
        bar.close()
    return poses


def _sources_attrs(stream: FrameStream) -> list[dict[str, Any]]:
    """Per input recording: its fingerprint, format and the topics read (the ``sources`` attribute)."""
    return [{**source_fingerprint(path), "format": plan.summary.format_name, "depth_topic": plan.depth.topic,
             "depth_encoding": plan.depth_encoding, "camera_info_topic": plan.camera_info.topic,
             "pose_topic": plan.pose.topic or "tf", "tf_topics": plan.tf_topics}
            for path, plan in zip(stream.paths, stream.plans, strict=True)]


def _frames_attrs(stream: FrameStream, width: int, height: int, sources: list[dict[str, Any]],
                  dropped: dict[str, int]) -> dict[str, Any]:
    """The attributes of frames.zarr (DESIGN.md): version, intrinsics, frames, sources, counts, parameters."""
    plan0 = stream.plans[0]
    return {
        "mapkit_version": __version__,
        "kind": "mapkit.frames",
        "K": stream.K.tolist(),
        "width": int(width),
        "height": int(height),
        "world_frame": plan0.world_frame,
        "body_frame": plan0.body_frame,
        "camera_frame": plan0.camera_frame,
        "sources": sources,
        "dropped": dropped,
        "depth_messages": stream.depth_messages,
        "units": {"depth": "m", "stamp_ns": "ns", "T_world_camera": "m"},
        "parameters": json.loads(json.dumps(stream.config.to_attrs())),
    }


def ingest(paths: Sequence[str | Path], workspace: str | Path, config: IngestConfig | None = None, *,
           overwrite: bool = False, progress: bool = True) -> IngestSummary:
    """Read recordings into ``workspace/frames.zarr`` (published atomically; `workspace` may be an
    fsspec URL, see docs/stores.md)."""
    config = config or IngestConfig()
    target = Location.of(workspace) / FRAMES
    check_store_writable(target, overwrite=overwrite)
    t0 = time.perf_counter()
    stream = open_frames(paths, config)
    with publish_store(target, overwrite=overwrite) as tmp:
        summary = write_frames(stream, tmp, progress=progress)
    summary.path = target.local if target.local is not None else target.url
    summary.seconds = time.perf_counter() - t0
    return summary


@dataclass
class FramesStore:
    """Read access to frames.zarr; depth is read lazily, one frame or slice at a time."""

    path: Path | str
    """The store: a local path, or its URL."""
    depth: Any
    """zarr array [N, H, W] float32 metres, NaN invalid."""
    stamp_ns: NDArray[np.int64]
    T_world_camera: NDArray[np.float64]
    T_world_body: NDArray[np.float64]
    source_index: NDArray[np.int32]
    K: NDArray[np.float64]
    attrs: dict[str, Any]

    def __len__(self) -> int:
        return len(self.stamp_ns)

    @property
    def width(self) -> int:
        return int(self.attrs["width"])

    @property
    def height(self) -> int:
        return int(self.attrs["height"])

    def is_current(self, paths: Sequence[str | Path], config: IngestConfig) -> bool:
        """True when this store was made from exactly these (unchanged) inputs with `config`."""
        wanted = [source_fingerprint(Path(p)) for p in paths]
        have = [{k: s[k] for k in ("path", "bytes", "mtime_ns")} for s in self.attrs.get("sources", [])]
        params = json.loads(json.dumps(config.to_attrs()))
        return wanted == have and params == self.attrs.get("parameters")


def open_frames_store(workspace: str | Path | Location) -> FramesStore:
    """Open ``workspace/frames.zarr`` (or a frames.zarr path or URL) written by `ingest`."""
    import zarr

    loc = Location.of(workspace)
    if loc.name != FRAMES:
        loc = loc / FRAMES
    path: Path | str = loc.local if loc.local is not None else loc.url
    try:
        if not loc.exists():
            raise IngestError(f"{str(path)!r} does not exist; run `mapkit ingest BAG... -w {loc.parent}` first")
        loc.require_complete(f"mapkit ingest BAG... -w {loc.parent} --overwrite")
    except StoreError as exc:
        raise IngestError(str(exc)) from None
    try:
        root = zarr.open_group(loc.zarr_store(read_only=True), mode="r")
        attrs = dict(root.attrs)
        if attrs.get("kind") != "mapkit.frames":
            raise KeyError("kind")
        names = ("stamp_ns", "T_world_camera", "T_world_body", "source_index")
        stamps, T_wc, T_wb, index = (read_whole(root, name) for name in names)
        return FramesStore(path, root["depth"], stamps, T_wc, T_wb, index, np.asarray(attrs["K"], np.float64), attrs)
    except Exception as exc:  # noqa: BLE001 - zarr raises many kinds for a damaged or foreign store
        raise IngestError(f"{str(path)!r} is not a mapkit frames store ({type(exc).__name__}: {exc}); re-run "
                          "`mapkit ingest --overwrite`") from None
