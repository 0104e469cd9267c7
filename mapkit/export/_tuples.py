"""`mapkit export`: frames.zarr + map.zarr → tuples.zarr (depth, poses, goals, split) for training."""

from __future__ import annotations

import hashlib
import itertools
import json
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import NDArray

from mapkit._stores import Location, check_store_writable, publish_store, store_files
from mapkit._version import __version__
from mapkit.errors import MapkitError
from mapkit.geometry import invert_transform
from mapkit.workspace import FRAMES

if TYPE_CHECKING:
    from mapkit.esdf import EsdfMap
    from mapkit.esdf._map import Outside
    from mapkit.ingest import FramesStore

TUPLES = "tuples.zarr"
FUTURE, RANDOM, HIDDEN = 0, 1, 2  # goal_kind values: future pose, visible free space, hidden behind obstacles
GOAL_KIND_NAMES = {FUTURE: "future_pose", RANDOM: "visible_free", HIDDEN: "hidden"}
_DISTANCE_BINS = (0.0, 2.0, 4.0, 6.0, 8.0, 10.0, float("inf"))


class ExportError(MapkitError):
    """A workspace that cannot be exported; the message says which store or option and why."""


@dataclass
class ExportConfig:
    """Options of `mapkit export`: each field is a setting (`mapkit config export`)."""

    goals_per_frame: int = 5
    """Goals stored per frame, split by ``goal_mix``."""
    goal_mix: tuple[float, float, float] = (0.2, 0.4, 0.4)
    """Shares of (future poses, visible free-space goals, hidden goals). Hidden goals lie in observed
    free space whose straight line from the body is blocked in the map (what evaluation asks for);
    a frame with too few of them gets visible goals instead (counted in the summary)."""
    goal_range: tuple[float, float] = (2.0, 8.0)
    """Metres from the camera within which visible and hidden goals are drawn."""
    hidden_bearing_deg: float = 75.0
    """Hidden goals lie within this horizontal angle of the body's forward axis (beyond the camera's
    field of view, as a goal seen over the shoulder after a detour)."""
    hidden_height: float = 1.0
    """Metres: hidden goals lie within this height of the body."""
    blocked_distance: float = 0.3
    """A goal is blocked when the map's distance along its straight line drops below this (metres;
    the robot radius)."""
    future_horizon: tuple[float, float] = (1.0, 5.0)
    """Seconds ahead along the flight from which future-pose goals are taken (iPlanner style)."""
    clearance: float = 0.3
    """Metres of signed distance a goal must keep from every obstacle."""
    val_fraction: float = 0.2
    """Share of contiguous flight segments held out for validation."""
    segment_seconds: float = 2.0
    """Length of the contiguous segments the split assigns whole (neighbouring frames are near
    duplicates, so a random per-frame split would leak)."""
    seed: int = 0
    """Seed of the goal sampling and the split."""
    stride: int = 1
    """Export every stride-th frame."""

    def validate(self) -> None:
        lo, hi = self.goal_range
        if not (np.isfinite(hi) and 0 < lo < hi):
            raise ExportError(f"goal_range {lo} {hi}: need 0 < min < max metres")
        a, b = self.future_horizon
        if not (np.isfinite(b) and 0 < a <= b):
            raise ExportError(f"future_horizon {a} {b}: need 0 < min <= max seconds")
        mix = tuple(float(v) for v in self.goal_mix)
        if len(mix) != 3 or not all(np.isfinite(v) and v >= 0 for v in mix) or sum(mix) <= 0:
            raise ExportError(f"goal_mix {self.goal_mix}: need three shares >= 0 (future visible hidden) with a positive sum")
        if not (0 < self.hidden_bearing_deg <= 180):
            raise ExportError(f"hidden_bearing_deg {self.hidden_bearing_deg} must be in (0, 180] degrees")
        for name in ("hidden_height", "blocked_distance"):
            v = getattr(self, name)
            if not (np.isfinite(v) and v > 0):
                raise ExportError(f"{name} {v} must be a positive number of metres")
        if self.goals_per_frame < 1:
            raise ExportError(f"goals_per_frame {self.goals_per_frame} must be at least 1")
        if not (0 <= self.val_fraction < 1):
            raise ExportError(f"val_fraction {self.val_fraction} must be in [0, 1)")
        if not self.segment_seconds > 0:
            raise ExportError(f"segment_seconds {self.segment_seconds} must be positive")
        if not (np.isfinite(self.clearance) and self.clearance >= 0):
            raise ExportError(f"clearance {self.clearance} must be >= 0 metres")
        if self.stride < 1:
            raise ExportError(f"stride {self.stride} must be at least 1")


@dataclass
class ExportSummary:
    path: Path | str
    """tuples.zarr: a local path, or the URL it was published at."""
    frames: int
    train: int
    val: int
    goals: int
    future_goals: int
    dropped_frames: int
    seconds: float
    kind_counts: dict[str, int] = field(default_factory=dict)
    """Goals per kind (future_pose, visible_free, hidden)."""
    blocked_fraction: float = 0.0
    """Share of goals whose straight line is blocked in the map."""
    distance_histogram: dict[str, int] = field(default_factory=dict)
    """Goal distances from the body, metres, binned ("0-2", "2-4", ...)."""

    def mix_dict(self) -> dict:
        """The goal mix as plain data (kinds, blocked share, distance histogram)."""
        return {"kinds": self.kind_counts, "blocked_fraction": self.blocked_fraction,
                "distance_histogram": self.distance_histogram}

    def mix_text(self) -> str:
        """One line: kinds, blocked share and distances."""
        kinds = ", ".join(f"{v} {k}" for k, v in self.kind_counts.items())
        hist = " ".join(f"{k}:{v}" for k, v in self.distance_histogram.items())
        return f"goals {kinds}; {100 * self.blocked_fraction:.0f} % blocked; distance m {hist}"


def map_digest(map_path: str | Path | Location) -> str:
    """sha256 over the map store's files (names and bytes): the tuples' reference to their map (the same
    for a local map and its copy at a URL)."""
    h = hashlib.sha256()
    for rel, data in store_files(Location.of(map_path)):
        h.update(rel.encode())
        h.update(data)
    return h.hexdigest()


def body_velocities(stamps_ns: NDArray[np.int64], T_world_body: NDArray[np.float64],
                    source_index: NDArray[np.int32] | None = None) -> NDArray[np.float64]:
    """(N, 3) body-frame velocity from the pose history (central differences; one-sided at ends),
    per recording when ``source_index`` is given (two flights' frames never difference each other)."""
    sources = np.zeros(len(stamps_ns), dtype=np.int32) if source_index is None else np.asarray(source_index)
    v_world = np.zeros((len(stamps_ns), 3))
    for src in np.unique(sources):
        sel = np.flatnonzero(sources == src)
        if len(sel) >= 2:
            v_world[sel] = np.gradient(T_world_body[sel, :3, 3], stamps_ns[sel].astype(np.float64) * 1e-9, axis=0)
    return np.einsum("nji,nj->ni", T_world_body[:, :3, :3], v_world)  # R^T v


def split_segments(stamps_ns: NDArray[np.int64], source_index: NDArray[np.int32], config: ExportConfig) -> NDArray[np.uint8]:
    """0 = train, 1 = validation, assigned per contiguous segment of `segment_seconds` per input."""
    rng = np.random.default_rng(config.seed)
    seg_id = np.zeros(len(stamps_ns), dtype=np.int64)
    next_id = 0
    for src in np.unique(source_index):
        sel = np.flatnonzero(source_index == src)
        t = (stamps_ns[sel] - stamps_ns[sel].min()) * 1e-9
        seg_id[sel] = next_id + (t // config.segment_seconds).astype(np.int64)
        next_id = int(seg_id[sel].max()) + 1
    segments = np.unique(seg_id)
    n_val = int(round(config.val_fraction * len(segments)))
    if config.val_fraction > 0 and len(segments) >= 2:
        n_val = max(n_val, 1)
    val = rng.choice(segments, size=min(n_val, len(segments) - 1), replace=False) if n_val else np.empty(0, int)
    return np.isin(seg_id, val).astype(np.uint8)


def blocked_lines(start: NDArray[np.float64], goals: NDArray[np.float64], esdf: EsdfMap | _ObservedMap, *, threshold: float,
                  step: float = 0.1) -> NDArray[np.bool_]:
    """(N,) True where the straight segment ``start`` (3,) → goal (N, 3) passes closer than
    ``threshold`` metres to an obstacle of the map (sampled every ``step`` metres; outside the map
    counts as free)."""
    goals = np.atleast_2d(goals)
    if not len(goals):
        return np.zeros(0, dtype=bool)
    n = max(2, int(np.ceil(np.linalg.norm(goals - start, axis=1).max() / step)) + 1)
    frac = np.linspace(0.0, 1.0, n)
    pts = start[None, None] + frac[None, :, None] * (goals - start)[:, None]
    d, _ = esdf.query(pts.reshape(-1, 3), outside="nan")
    d = np.where(np.isfinite(d), d, np.inf).reshape(len(goals), n)
    return d.min(axis=1) < threshold


def _goal_counts(config: ExportConfig) -> tuple[int, int]:
    """(future, hidden) goals per frame from the mix, rounded (visible goals take the rest)."""
    mix = np.asarray(config.goal_mix, dtype=np.float64)
    mix = mix / mix.sum()
    want = config.goals_per_frame
    future = int(round(want * mix[0]))
    hidden = min(want - future, int(round(want * mix[2])))
    return future, hidden


def _future_goals(i: int, count: int, *, frames_T_wb: NDArray[np.float64], stamps_s: NDArray[np.float64],
                  source_index: NDArray[np.int32], esdf: _ObservedMap, config: ExportConfig,
                  rng: np.random.Generator) -> list[tuple[NDArray[np.float64], float]]:
    """Up to ``count`` future poses of the same flight, ``future_horizon`` seconds ahead, with clearance."""
    dt = stamps_s - stamps_s[i]
    lo, hi = config.future_horizon
    future = np.flatnonzero((dt >= lo) & (dt <= hi) & (source_index == source_index[i]))
    if not len(future) or count <= 0:
        return []
    pts = frames_T_wb[rng.choice(future, size=min(len(future), count), replace=False), :3, 3]
    d, _ = esdf.query(pts, outside="nan")
    return [(p, float(di)) for p, di in zip(pts, d, strict=True) if np.isfinite(di) and di >= config.clearance]


def _visible_goals(count: int, *, T_world_camera: NDArray[np.float64], depth: NDArray[np.float32],
                   K: NDArray[np.float64], esdf: _ObservedMap, config: ExportConfig,
                   rng: np.random.Generator) -> list[tuple[NDArray[np.float64], float]]:
    """Up to ``count`` goals in the camera's view, in front of the measured depth along their pixel's
    ray, in observed free space with clearance."""
    H, W = depth.shape

    def draw(need: int) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        n = 16 * need
        u = rng.uniform(0, W - 1, n)
        v = rng.uniform(0, H - 1, n)
        r = rng.uniform(config.goal_range[0], config.goal_range[1], n)
        ray = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones(n)], axis=1)
        ray /= np.linalg.norm(ray, axis=1, keepdims=True)
        z = r * ray[:, 2]
        measured = depth[np.rint(v).astype(int), np.rint(u).astype(int)]
        front = ~np.isfinite(measured) | (z < measured - config.clearance)
        pts = (T_world_camera[:3, :3] @ (ray * r[:, None]).T).T + T_world_camera[:3, 3]
        d, _ = esdf.query(pts, outside="nan")
        ok = front & np.isfinite(d) & (d >= config.clearance) & esdf.observed_at(pts)
        return pts[ok], d[ok]

    return _draw_until(count, 8, draw)


def _hidden_goals(count: int, *, T_world_body: NDArray[np.float64], esdf: _ObservedMap, config: ExportConfig,
                  rng: np.random.Generator) -> list[tuple[NDArray[np.float64], float]]:
    """Up to ``count`` goals in observed free space (with clearance) within ``hidden_bearing_deg`` of
    the body's heading, whose straight line from the body is blocked in the map."""
    p0 = T_world_body[:3, 3]
    yaw = float(np.arctan2(T_world_body[1, 0], T_world_body[0, 0]))
    half = np.deg2rad(config.hidden_bearing_deg)

    def draw(need: int) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        n = 24 * need
        bearing = yaw + rng.uniform(-half, half, n)
        r = rng.uniform(config.goal_range[0], config.goal_range[1], n)
        dz = rng.uniform(-config.hidden_height, config.hidden_height, n)
        pts = p0 + np.stack([r * np.cos(bearing), r * np.sin(bearing), dz], axis=1)
        d, _ = esdf.query(pts, outside="nan")
        ok = np.isfinite(d) & (d >= config.clearance) & esdf.observed_at(pts)
        pts, d = pts[ok], d[ok]
        hit = blocked_lines(p0, pts, esdf, threshold=config.blocked_distance)
        return pts[hit], d[hit]

    return _draw_until(count, 6, draw)


def _draw_until(count: int, tries: int, draw: Any) -> list[tuple[NDArray[np.float64], float]]:
    """Up to ``count`` (goal, clearance) pairs from at most ``tries`` calls of ``draw(still needed)``."""
    out: list[tuple[NDArray[np.float64], float]] = []
    for _ in range(tries):
        need = count - len(out)
        if need <= 0:
            break
        pts, d = draw(need)
        out.extend((p, float(di)) for p, di in zip(pts[:need], d[:need], strict=True))
    return out


def _sample_goals(
    i: int, *, frames_T_wb: NDArray[np.float64], stamps_s: NDArray[np.float64], source_index: NDArray[np.int32],
    T_world_camera: NDArray[np.float64], depth: NDArray[np.float32], K: NDArray[np.float64],
    esdf: _ObservedMap, config: ExportConfig, rng: np.random.Generator,
) -> tuple[list[NDArray[np.float64]], list[int], list[float]]:
    """Up to goals_per_frame world-frame goals for frame i in the configured mix; kinds short of
    candidates are made up with visible free-space goals."""
    n_future, n_hidden = _goal_counts(config)
    future = _future_goals(i, n_future, frames_T_wb=frames_T_wb, stamps_s=stamps_s, source_index=source_index,
                           esdf=esdf, config=config, rng=rng)
    hidden = _hidden_goals(n_hidden, T_world_body=frames_T_wb[i], esdf=esdf, config=config, rng=rng)
    visible = _visible_goals(config.goals_per_frame - len(future) - len(hidden), T_world_camera=T_world_camera, depth=depth, K=K, esdf=esdf, config=config,
                             rng=rng)
    picked = [(FUTURE, future), (RANDOM, visible), (HIDDEN, hidden)]
    goals = [p for _, items in picked for p, _ in items]
    kinds = [k for k, items in picked for _ in items]
    clear = [c for _, items in picked for _, c in items]
    return goals, kinds, clear


def export_tuples(workspace: str | Path, config: ExportConfig | None = None, *, overwrite: bool = False, progress: bool = True) -> ExportSummary:
    """Write ``workspace/tuples.zarr`` from ``frames.zarr`` and ``map.zarr`` (atomically)."""
    from mapkit.esdf import MAP

    config = config or ExportConfig()
    config.validate()
    ws = Location.of(workspace)
    target = ws / TUPLES
    check_store_writable(target, overwrite=overwrite)
    if not (ws / MAP).exists():
        raise ExportError(f"{ws / MAP} does not exist; run `mapkit fuse` and `mapkit esdf -w {ws}` before export")
    if not (ws / FRAMES).exists():
        raise ExportError(f"{ws / FRAMES} does not exist; run `mapkit ingest` (or `mapkit fuse`) first")
    t0 = time.perf_counter()
    store, esdf = _open_inputs(ws)
    indices = np.arange(0, len(store), config.stride)
    velocity = body_velocities(store.stamp_ns, store.T_world_body, store.source_index)
    goals = _collect_goals(store, esdf, indices, config, progress=progress)
    sel = np.asarray(goals.frame_index)
    split = split_segments(store.stamp_ns[sel], store.source_index[sel], config)
    digest = map_digest(ws / MAP)
    with publish_store(target, overwrite=overwrite) as tmp:
        root = _write_tuples(tmp, store, sel, velocity, goals, split, progress=progress)
        root.attrs.update(_tuples_attrs(ws, store, esdf, config, digest))
    return _summary(target.local if target.local is not None else target.url, goals, split, n_indices=len(indices), seconds=time.perf_counter() - t0)


def _open_inputs(ws: Location) -> tuple[FramesStore, _ObservedMap]:
    """frames.zarr and map.zarr of ``ws``; raises unless they share a frame and the cameras lie in the map."""
    from mapkit.esdf import MAP, EsdfMap
    from mapkit.ingest import open_frames_store

    store = open_frames_store(ws)
    esdf = _ObservedMap(EsdfMap.open(ws / MAP))
    if esdf.frame_id != store.attrs.get("world_frame"):
        raise ExportError(
            f"map.zarr is in frame {esdf.frame_id!r} but frames.zarr in {store.attrs.get('world_frame')!r}; "
            "rebuild the map from these frames (mapkit fuse/esdf --overwrite)"
        )
    lo, hi = esdf.map.bounds
    cams = store.T_world_camera[:, :3, 3]
    inside = np.all((cams >= lo) & (cams <= hi), axis=1)
    if not inside.any():
        raise ExportError(
            f"no camera position of frames.zarr lies inside map.zarr's bounds {lo.round(2).tolist()}–{hi.round(2).tolist()}; "
            "the map was built from other frames: rebuild it (mapkit fuse/esdf --overwrite)"
        )
    return store, esdf


@dataclass
class _Goals:
    """The goals of the frames kept (those with ``goals_per_frame`` valid goals), one entry per frame."""

    frame_index: list[int] = field(default_factory=list)
    goals_body: list[NDArray[np.float32]] = field(default_factory=list)
    kinds: list[NDArray[np.uint8]] = field(default_factory=list)
    clearance: list[NDArray[np.float32]] = field(default_factory=list)
    blocked: list[NDArray[np.uint8]] = field(default_factory=list)


def _collect_goals(store: FramesStore, esdf: _ObservedMap, indices: NDArray[np.int64], config: ExportConfig, *,
                   progress: bool) -> _Goals:
    """Sample goals for every frame at ``indices`` (one seeded generator, in frame order); raises when no
    frame has enough."""
    from tqdm import tqdm

    stamps_s = store.stamp_ns.astype(np.float64) * 1e-9
    rng = np.random.default_rng(config.seed)
    out = _Goals()
    for i in tqdm(indices, desc="goals", unit="frame", disable=not progress):
        depth = np.asarray(store.depth[int(i)])
        goals, kinds, clear = _sample_goals(
            int(i), frames_T_wb=store.T_world_body, stamps_s=stamps_s, source_index=store.source_index,
            T_world_camera=store.T_world_camera[i], depth=depth, K=store.K, esdf=esdf, config=config, rng=rng,
        )
        if len(goals) < config.goals_per_frame:
            continue  # a frame with too few valid goals is left out (counted in the summary)
        T_body_world = invert_transform(store.T_world_body[i])
        pts = np.asarray(goals)
        out.goals_body.append((pts @ T_body_world[:3, :3].T + T_body_world[:3, 3]).astype(np.float32))
        out.kinds.append(np.asarray(kinds, dtype=np.uint8))
        out.clearance.append(np.asarray(clear, dtype=np.float32))
        out.blocked.append(blocked_lines(store.T_world_body[i, :3, 3], pts, esdf,
                                         threshold=config.blocked_distance).astype(np.uint8))
        out.frame_index.append(int(i))
    if not out.frame_index:
        frac = float(np.asarray(esdf.map.observed[:]).mean())
        raise ExportError(
            f"no valid goals in any of {len(indices)} frames: no observed free space with {config.clearance} m clearance "
            f"within goal_range {config.goal_range[0]}–{config.goal_range[1]} m in front of the camera "
            f"(observed voxels: {100 * frac:.1f} %); lower clearance or change goal_range (--set clearance=M)"
        )
    return out


def _write_tuples(path: Location, store: FramesStore, sel: NDArray[np.int64], velocity: NDArray[np.float64],
                  goals: _Goals, split: NDArray[np.uint8], *, progress: bool) -> Any:
    """The arrays of tuples.zarr at ``path``: the kept frames' depth (in batches of 32), poses, goals, split."""
    import zarr
    from tqdm import tqdm
    from zarr.codecs import BloscCodec

    root = zarr.open_group(path.zarr_store(read_only=False), mode="w-", zarr_format=3)
    H, W = store.height, store.width
    depth_out = root.create_array(
        "depth", shape=(len(sel), H, W), chunks=(1, H, W), dtype="float32", fill_value=float("nan"),
        compressors=[BloscCodec(cname="lz4", clevel=1, shuffle="bitshuffle")], dimension_names=["tuple", "v", "u"],
    )
    for start in tqdm(range(0, len(sel), 32), desc="depth", unit="batch", disable=not progress):
        part = sel[start : start + 32]
        depth_out[start : start + len(part)] = np.stack([np.asarray(store.depth[int(j)]) for j in part])

    def small(name: str, data: NDArray, dims: list[str]) -> None:
        root.create_array(name, data=data, dimension_names=dims)

    small("frame_index", sel.astype(np.int32), ["tuple"])
    small("stamp_ns", store.stamp_ns[sel], ["tuple"])
    small("source_index", store.source_index[sel], ["tuple"])
    small("T_world_body", store.T_world_body[sel], ["tuple", "row", "col"])
    small("T_world_camera", store.T_world_camera[sel], ["tuple", "row", "col"])
    small("velocity_body", velocity[sel].astype(np.float32), ["tuple", "xyz"])
    small("goals_body", np.stack(goals.goals_body), ["tuple", "goal", "xyz"])
    small("goal_kind", np.stack(goals.kinds), ["tuple", "goal"])
    small("goal_clearance", np.stack(goals.clearance), ["tuple", "goal"])
    small("goal_blocked", np.stack(goals.blocked), ["tuple", "goal"])
    small("split", split, ["tuple"])
    return root


def _where(loc: Location) -> str:
    """How tuples.zarr names its inputs: an absolute local path, or the URL."""
    return str(loc.local.resolve()) if loc.local is not None else loc.url


def _tuples_attrs(ws: Location, store: FramesStore, esdf: _ObservedMap, config: ExportConfig, digest: str) -> dict[str, Any]:
    """The attributes of tuples.zarr: version, camera, frames, the map it was made from, goal codes, parameters."""
    from mapkit.esdf import MAP

    return {
        "mapkit_version": __version__,
        "kind": "mapkit.tuples",
        "K": store.K.tolist(),
        "width": store.width,
        "height": store.height,
        "world_frame": store.attrs.get("world_frame"),
        "body_frame": store.attrs.get("body_frame"),
        "map": {"path": _where(ws / MAP), "sha256": digest, "voxel_size": esdf.map.voxel_size},
        "frames": _where(ws / FRAMES),
        "goal_kinds": {name: code for code, name in GOAL_KIND_NAMES.items()},
        "split_values": {"train": 0, "val": 1},
        "parameters": json.loads(json.dumps(asdict(config))),
        "units": {"goals_body": "m (body frame FLU)", "velocity_body": "m/s (body frame)", "depth": "m"},
    }


def _summary(target: Path | str, goals: _Goals, split: NDArray[np.uint8], *, n_indices: int, seconds: float) -> ExportSummary:
    """Counts of tuples, splits and goals, the goal mix and the distance histogram."""
    kinds = np.stack(goals.kinds)
    distance = np.linalg.norm(np.stack(goals.goals_body), axis=-1)
    counts, _ = np.histogram(distance, bins=_DISTANCE_BINS)
    labels = [f"{lo:g}-{hi:g}" if np.isfinite(hi) else f">{lo:g}" for lo, hi in itertools.pairwise(_DISTANCE_BINS)]
    n = len(goals.frame_index)
    return ExportSummary(
        target, n, int((split == 0).sum()), int((split == 1).sum()), int(kinds.size),
        int((kinds == FUTURE).sum()), n_indices - n, seconds,
        kind_counts={name: int((kinds == code).sum()) for code, name in GOAL_KIND_NAMES.items()},
        blocked_fraction=float(np.stack(goals.blocked).mean()),
        distance_histogram={k: int(v) for k, v in zip(labels, counts, strict=True)},
    )


class _ObservedMap:
    """EsdfMap plus nearest-voxel lookups of the observed mask (goals must lie in seen space)."""

    def __init__(self, esdf_map: EsdfMap) -> None:
        self.map = esdf_map
        self._observed = np.asarray(esdf_map.observed[:]).astype(bool)

    def __getattr__(self, name: str) -> object:
        return getattr(self.map, name)

    def query(self, points: NDArray[np.float64], *, outside: Outside = "nan") -> tuple[NDArray, NDArray]:
        return self.map.query(points, outside=outside)

    def observed_at(self, points: NDArray[np.float64]) -> NDArray[np.bool_]:
        idx = np.rint((points - self.map.origin) / self.map.voxel_size).astype(np.int64)
        shape = np.asarray(self._observed.shape)
        ok = np.all((idx >= 0) & (idx < shape), axis=1)
        out = np.zeros(len(points), dtype=bool)
        out[ok] = self._observed[tuple(idx[ok].T)]
        return out
