"""`mapkit export-foxglove`: one MCAP file that Foxglove opens with no configuration, written with the
``foxglove-sdk`` package at the recording's own stamps; the topics are listed in docs/exchange.md."""

from __future__ import annotations

import time
from collections import Counter
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from mapkit._formats import EpisodeRecord, Outcome
from mapkit.errors import MapkitError
from mapkit.geometry import invert_transform, quat_xyzw_from_matrix


class ExchangeError(MapkitError):
    """A workspace, model or output that an export cannot use."""


@dataclass(frozen=True)
class FoxgloveConfig:
    """What ``export_foxglove`` writes."""

    model: str | None = None
    """Run directory or "pretrained": plans at ``plan_count`` frames (None: no plans)."""
    eval_dir: Path | None = None
    """A `mapkit eval` output folder: its flown paths per method (None: none)."""
    plan_count: int = 12
    """Frames, evenly spread over the flight, that get a plan."""
    goal_ahead: float = 4.0
    """Seconds: each plan goes to where the flight was this much later (the local goal a planner got)."""
    voxel_limit: int = 2_000_000
    """Largest ESDF written as one VoxelGrid; Foxglove draws every cell, and past a few million the 3D
    panel stalls. Larger maps become Grid slices at ``slice_heights``."""
    slice_heights: tuple[float, ...] = (0.5, 1.0, 1.5, 2.0)
    """Metres (world z) of the ESDF slices written instead of a too-large VoxelGrid."""
    overwrite: bool = False

    def validate(self) -> None:
        if self.plan_count < 1:
            raise ExchangeError(f"--plans {self.plan_count} must be at least 1")
        if not (np.isfinite(self.goal_ahead) and self.goal_ahead > 0):
            raise ExchangeError(f"--goal-ahead {self.goal_ahead} must be a positive number of seconds")
        if self.voxel_limit < 1:
            raise ExchangeError(f"voxel_limit {self.voxel_limit} must be at least 1")


@dataclass
class ExportSummary:
    """What an export wrote."""

    path: Path
    notes: list[str] = field(default_factory=list)
    """Layers left out, each with the command that makes them."""
    plans_skipped: Counter[str] = field(default_factory=Counter)
    """With a model: why some of the ``plan_count`` frames got no plan (reason → frames)."""
    bytes: int = 0
    seconds: float = 0.0


@dataclass
class FoxgloveSummary(ExportSummary):
    """What was written to the MCAP."""

    messages: dict[str, int] = field(default_factory=dict)
    """Topic → message count."""
    esdf_as: str = ""
    """"VoxelGrid", "Grid slices" or "" (no map)."""


def _vector_quaternion(T: NDArray[np.float64]) -> tuple[Any, Any]:
    """The translation and rotation of a 4x4 transform as Foxglove's Vector3 and Quaternion."""
    from foxglove.messages import Quaternion, Vector3

    q = quat_xyzw_from_matrix(T[:3, :3])
    return (Vector3(x=float(T[0, 3]), y=float(T[1, 3]), z=float(T[2, 3])),
            Quaternion(x=float(q[0]), y=float(q[1]), z=float(q[2]), w=float(q[3])))


def _pose(T: NDArray[np.float64]) -> Any:
    from foxglove.messages import Pose

    position, orientation = _vector_quaternion(T)
    return Pose(position=position, orientation=orientation)


def _stamp(ns: int) -> Any:
    from foxglove.messages import Timestamp

    return Timestamp(sec=int(ns) // 1_000_000_000, nsec=int(ns) % 1_000_000_000)


def _transform(ns: int, parent: str, child: str, T: NDArray[np.float64]) -> Any:
    from foxglove.messages import FrameTransform

    translation, rotation = _vector_quaternion(T)
    return FrameTransform(timestamp=_stamp(ns), parent_frame_id=parent, child_frame_id=child, translation=translation,
                          rotation=rotation)


def _fields(*spec: tuple[str, int, str]) -> list[Any]:
    from foxglove.messages import PackedElementField, PackedElementFieldNumericType

    return [PackedElementField(name=name, offset=offset, type=getattr(PackedElementFieldNumericType, kind))
            for name, offset, kind in spec]


def _height_colours(z: NDArray[np.float64]) -> NDArray[np.uint8]:
    """RGBA per point from a blue → red ramp over the cloud's 2nd–98th height percentiles."""
    lo, hi = np.percentile(z, [2, 98]) if len(z) else (0.0, 1.0)
    u = np.clip((z - lo) / max(hi - lo, 1e-6), 0.0, 1.0)
    rgba = np.stack([255 * u, 255 * (1 - np.abs(2 * u - 1)), 255 * (1 - u), np.full_like(u, 255)], axis=1)
    return rgba.astype(np.uint8)


def _log_flight(frames: Any, channels: dict[str, Any]) -> int:
    """World → body → camera transforms, depth (16UC1 mm, 0 invalid) and calibration per frame."""
    from foxglove.messages import CameraCalibration, FrameTransforms, RawImage

    world, body, camera = (str(frames.attrs.get(k) or d) for k, d in
                           (("world_frame", "world"), ("body_frame", "body"), ("camera_frame", "camera")))
    K = np.asarray(frames.K, dtype=np.float64)
    height, width = frames.depth.shape[1:]
    P = np.concatenate([K, np.zeros((3, 1))], axis=1)
    for i, ns in enumerate(frames.stamp_ns.tolist()):
        T_wb = frames.T_world_body[i]
        T_bc = invert_transform(T_wb) @ frames.T_world_camera[i]
        channels["/tf"].log(FrameTransforms(transforms=[_transform(ns, world, body, T_wb), _transform(ns, body, camera, T_bc)]),
                            log_time=ns)
        depth = np.asarray(frames.depth[i], dtype=np.float64)
        mm = np.where(np.isfinite(depth), np.clip(np.round(depth * 1000.0), 0, 65535), 0).astype("<u2")
        channels["/camera/depth"].log(RawImage(timestamp=_stamp(ns), frame_id=camera, width=width, height=height,
                                               encoding="16UC1", step=2 * width, data=mm.tobytes()), log_time=ns)
        channels["/camera/calibration"].log(CameraCalibration(
            timestamp=_stamp(ns), frame_id=camera, width=width, height=height, distortion_model="plumb_bob",
            D=[0.0] * 5, K=K.ravel().tolist(), R=np.eye(3).ravel().tolist(), P=P.ravel().tolist()), log_time=ns)
    return len(frames.stamp_ns)


def _log_cloud(path: Path, world: str, ns: int, channel: Any) -> None:
    import open3d as o3d
    from foxglove.messages import PointCloud

    points = np.asarray(o3d.io.read_point_cloud(path).points, dtype=np.float64)
    if not len(points):
        raise ExchangeError(f"{path} has no points; re-run `mapkit fuse --overwrite`")
    packed = np.zeros(len(points), dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("rgba", "u1", 4)])
    packed["x"], packed["y"], packed["z"] = points.T
    packed["rgba"] = _height_colours(points[:, 2])
    fields = _fields(("x", 0, "Float32"), ("y", 4, "Float32"), ("z", 8, "Float32"), ("red", 12, "Uint8"),
                     ("green", 13, "Uint8"), ("blue", 14, "Uint8"), ("alpha", 15, "Uint8"))
    channel.log(PointCloud(timestamp=_stamp(ns), frame_id=world, pose=_pose(np.eye(4)), point_stride=16,
                           fields=fields, data=packed.tobytes()), log_time=ns)


def _corner(esdf_map: Any) -> NDArray[np.float64]:
    """World pose of the grid's lower corner (voxel [0, 0, 0]'s centre minus half a voxel)."""
    T = np.eye(4)
    T[:3, 3] = np.asarray(esdf_map.origin) - 0.5 * esdf_map.voxel_size
    return T


def _log_esdf(esdf_map: Any, world: str, ns: int, channels: dict[str, Any], config: FoxgloveConfig) -> str:
    """The ESDF as one VoxelGrid (distance, observed), or Grid slices when it is too large."""
    from foxglove.messages import Grid, Vector2, Vector3, VoxelGrid

    nx, ny, nz = esdf_map.shape
    vs = float(esdf_map.voxel_size)
    cell = np.dtype([("distance", "<f4"), ("observed", "u1")])
    fields = _fields(("distance", 0, "Float32"), ("observed", 4, "Uint8"))
    observed = esdf_map.observed is not None
    if nx * ny * nz <= config.voxel_limit:
        data = np.zeros((nz, ny, nx), dtype=cell)  # Foxglove: depth (z), then rows (y), then cells (x)
        data["distance"] = esdf_map.read("esdf", ...).transpose(2, 1, 0)
        data["observed"] = esdf_map.read("observed", ...).transpose(2, 1, 0) if observed else 1
        channels["/map/esdf"].log(VoxelGrid(
            timestamp=_stamp(ns), frame_id=world, pose=_pose(_corner(esdf_map)), row_count=ny, column_count=nx,
            cell_size=Vector3(x=vs, y=vs, z=vs), slice_stride=cell.itemsize * nx * ny, row_stride=cell.itemsize * nx,
            cell_stride=cell.itemsize, fields=fields, data=data.tobytes()), log_time=ns)
        return "VoxelGrid"
    for z in config.slice_heights:
        k = int(round((z - esdf_map.origin[2]) / vs))
        if not 0 <= k < nz:
            continue
        data = np.zeros((ny, nx), dtype=cell)
        data["distance"] = esdf_map.read("esdf", (slice(None), slice(None), k)).T
        data["observed"] = esdf_map.read("observed", (slice(None), slice(None), k)).T if observed else 1
        T = _corner(esdf_map)
        T[2, 3] = esdf_map.origin[2] + k * vs
        channels["/map/esdf_slices"].log(Grid(
            timestamp=_stamp(ns), frame_id=world, pose=_pose(T), column_count=nx, cell_size=Vector2(x=vs, y=vs),
            row_stride=cell.itemsize * nx, cell_stride=cell.itemsize, fields=fields, data=data.tobytes()), log_time=ns)
    return "Grid slices"


def _colour(r: float, g: float, b: float, a: float = 1.0) -> Any:
    from foxglove.messages import Color

    return Color(r=r, g=g, b=b, a=a)


def _line(points_world: NDArray[np.float64], colour: Any, thickness: float = 0.04) -> Any:
    from foxglove.messages import LinePrimitive, LinePrimitiveLineType, Point3

    return LinePrimitive(type=LinePrimitiveLineType.LineStrip, pose=_pose(np.eye(4)), thickness=thickness,
                         scale_invariant=False, points=[Point3(x=float(x), y=float(y), z=float(z)) for x, y, z in points_world],
                         color=colour)


def _plan_entity(result: Any, T_wb: NDArray[np.float64], ns: int, world: str, index: int) -> Any:
    """Trajectory, key-points and one corridor box per key-point segment (body axes) of one plan."""
    from foxglove.messages import CubePrimitive, SceneEntity, SpherePrimitive, Vector3

    R, p = T_wb[:3, :3], T_wb[:3, 3]
    samples = result.samples_body @ R.T + p
    ends = np.concatenate([np.zeros((1, 3)), result.keypoints])
    spheres, cubes = [], []
    for k, kp in enumerate(result.keypoints):
        T = np.eye(4)
        T[:3, 3] = R @ kp + p
        spheres.append(SpherePrimitive(pose=_pose(T), size=Vector3(x=0.15, y=0.15, z=0.15), color=_colour(1.0, 0.6, 0.0)))
        lo, hi = np.minimum(ends[k], ends[k + 1]) - PLAN_CORRIDOR, np.maximum(ends[k], ends[k + 1]) + PLAN_CORRIDOR
        box = np.eye(4)
        box[:3, :3], box[:3, 3] = R, R @ (0.5 * (lo + hi)) + p
        size = hi - lo
        cubes.append(CubePrimitive(pose=_pose(box), size=Vector3(x=float(size[0]), y=float(size[1]), z=float(size[2])),
                                   color=_colour(0.2, 0.6, 1.0, 0.12)))
    colour = _colour(0.1, 0.8, 0.2) if result.execute else _colour(0.9, 0.1, 0.1)
    return SceneEntity(timestamp=_stamp(ns), frame_id=world, id=f"plan_{index:06d}", lines=[_line(samples, colour)],
                       spheres=spheres, cubes=cubes, metadata=[])


PLAN_CORRIDOR = 1.0
"""Metres: the flight corridor of exported plans (``mapkit eval``'s default, ``Corridor.width``)."""


HOVER_DISTANCE = 0.5
"""Metres: a goal this close leaves nowhere to plan to (the vehicle hovered); such frames get no plan."""


def _plan_results(frames: Any, config: FoxgloveConfig, skipped: Counter[str]
                  ) -> Iterator[tuple[int, NDArray[np.float64], Any]]:
    """(stamp, T_world_body, PlanResult) of ``config.model`` at evenly spread frames, each
    toward where the flight was ``goal_ahead`` seconds later (same recording), clipped to the
    planner's range; the ``plan_count`` frames that get none are counted in ``skipped`` by reason,
    for the summary to say why fewer plans were written."""
    from mapkit.export import body_velocities
    from mapkit.flight import FlightError, Planner
    from mapkit.flight._single import LOCAL_GOAL_RANGE

    try:
        planner = Planner.load(str(config.model))
    except FlightError as exc:
        raise ExchangeError(f"--model: {exc}") from None
    stamps = frames.stamp_ns.astype(np.int64)
    velocity = body_velocities(stamps, frames.T_world_body, frames.source_index)
    picks = np.unique(np.linspace(0, len(stamps) - 1, config.plan_count).round().astype(int)).tolist()
    if len(picks) < config.plan_count:  # evenly spread over fewer frames than plans: each frame once
        skipped[f"the flight has only {len(stamps)} frames"] += config.plan_count - len(picks)
    for i in picks:
        later = np.flatnonzero((frames.source_index == frames.source_index[i]) & (stamps >= stamps[i] + int(config.goal_ahead * 1e9)))
        if not len(later):
            skipped[f"no frame {config.goal_ahead:g} s later in its recording to plan toward (the flight's end, "
                    "see --goal-ahead)"] += 1
            continue
        T_wb = frames.T_world_body[i]
        goal = (invert_transform(T_wb) @ np.append(frames.T_world_body[later[0]][:3, 3], 1.0))[:3]
        distance = float(np.linalg.norm(goal))
        if distance < HOVER_DISTANCE:
            skipped[f"under {HOVER_DISTANCE:g} m flown in the next {config.goal_ahead:g} s: nowhere to plan to "
                    "(hovering, or a short --goal-ahead)"] += 1
            continue
        result = planner.plan(np.asarray(frames.depth[i]), goal * min(1.0, LOCAL_GOAL_RANGE / distance),
                              velocity_body=velocity[i], corridor=PLAN_CORRIDOR, K=frames.K,
                              T_body_camera=invert_transform(T_wb) @ frames.T_world_camera[i])
        yield int(stamps[i]), T_wb, result


def _log_plans(frames: Any, world: str, config: FoxgloveConfig, channel: Any, skipped: Counter[str]) -> int:
    from foxglove.messages import SceneUpdate

    count = 0
    for ns, T_wb, result in _plan_results(frames, config, skipped):
        channel.log(SceneUpdate(entities=[_plan_entity(result, T_wb, ns, world, count)]), log_time=ns)
        count += 1
    return count


_OUTCOME_COLOURS = {"success": (0.1, 0.7, 0.2), "collision": (0.9, 0.1, 0.1), "timeout": (1.0, 0.6, 0.0)}


def read_eval_paths(eval_dir: Path) -> list[tuple[str, str, NDArray[np.float64], tuple[float, float, float]]]:
    """(world, method, flown xyz points, RGB colour of its outcome) of every path of a `mapkit eval` folder."""
    import json

    try:
        rows = json.loads((eval_dir / "results.json").read_text()).get("episodes", [])
        records = [EpisodeRecord.from_dict(row) for row in rows]
        paths = np.load(eval_dir / "trajectories.npz")
    except (OSError, ValueError, KeyError, TypeError, AttributeError) as exc:
        raise ExchangeError(f"--eval {eval_dir}: not a readable `mapkit eval` folder ({type(exc).__name__}: {exc}); "
                            f"run `mapkit eval -o {eval_dir}` first") from None
    outcome: dict[tuple[str, int, str], Outcome] = {(r.world, int(r.pair), r.method): r.outcome for r in records}
    out = []
    for key in paths.files:
        world, pair, method = key.split("/")
        colour = _OUTCOME_COLOURS.get(outcome.get((world, int(pair), method), ""), (0.5, 0.5, 0.5))
        out.append((world, method, paths[key][:, 1:4], colour))
    return out


def _log_eval(eval_dir: Path, ns: int, channels: dict[str, Any], context: Any) -> int:
    """Every flown path of a `mapkit eval` folder: one topic per method, one entity per world, in
    frame ``eval/<world>`` (the evaluation's own simulated worlds, not the workspace's)."""
    from foxglove.channels import SceneUpdateChannel
    from foxglove.messages import SceneEntity, SceneUpdate

    lines: dict[str, dict[str, list[Any]]] = {}
    for world, method, points, colour in read_eval_paths(eval_dir):
        lines.setdefault(method, {}).setdefault(world, []).append(_line(points, _colour(*colour), 0.03))
    for method, worlds in sorted(lines.items()):
        topic = f"/eval/{method}"
        channels[topic] = SceneUpdateChannel(topic, context=context)
        channels[topic].log(SceneUpdate(entities=[SceneEntity(timestamp=_stamp(ns), frame_id=f"eval/{world}", id=world,
                                                              lines=world_lines, metadata=[])
                                                  for world, world_lines in sorted(worlds.items())]), log_time=ns)
    return len(lines)


def export_foxglove(workspace: str | Path, output: str | Path, config: FoxgloveConfig = FoxgloveConfig()) -> FoxgloveSummary:
    """Write the workspace's flight, cloud, ESDF (and plans, evaluation paths) to ``output`` (.mcap),
    atomically; see the module docstring for the topics."""
    import foxglove
    from foxglove.channels import (
        CameraCalibrationChannel,
        FrameTransformsChannel,
        GridChannel,
        PointCloudChannel,
        RawImageChannel,
        SceneUpdateChannel,
        VoxelGridChannel,
    )

    from mapkit.esdf import MAP, EsdfMap
    from mapkit.fusion import CLOUD
    from mapkit.workspace import atomic_output

    t0 = time.perf_counter()
    workspace, output = Path(workspace), Path(output)
    frames = open_inputs(workspace, output, ".mcap", config)
    esdf_map = EsdfMap.open(workspace / MAP) if (workspace / MAP).exists() else None
    world = str(frames.attrs.get("world_frame") or "world")
    first = int(frames.stamp_ns[0])
    summary = FoxgloveSummary(output)
    context = foxglove.Context()
    kinds = {"/tf": FrameTransformsChannel, "/camera/depth": RawImageChannel,
             "/camera/calibration": CameraCalibrationChannel, "/map/cloud": PointCloudChannel,
             "/map/esdf": VoxelGridChannel, "/map/esdf_slices": GridChannel, "/planner/plans": SceneUpdateChannel}
    channels: dict[str, Any] = {topic: kind(topic, context=context) for topic, kind in kinds.items()}
    with atomic_output(output, overwrite=config.overwrite) as tmp:
        writer = foxglove.open_mcap(tmp, context=context)
        try:
            summary.messages["/tf"] = _log_flight(frames, channels)
            if (workspace / CLOUD).exists():
                _log_cloud(workspace / CLOUD, world, first, channels["/map/cloud"])
            summary.notes = missing_layers(workspace)
            if esdf_map is not None:
                summary.esdf_as = _log_esdf(esdf_map, world, first, channels, config)
                if summary.esdf_as == "Grid slices":
                    summary.notes.append(
                        f"the ESDF has {int(np.prod(esdf_map.shape)):,} voxels, more than one VoxelGrid message holds "
                        f"well ({config.voxel_limit:,}); wrote Grid slices at z = "
                        f"{', '.join(f'{z:g}' for z in config.slice_heights)} m on /map/esdf_slices instead")
            if config.model is not None:
                summary.messages["/planner/plans"] = _log_plans(frames, world, config, channels["/planner/plans"],
                                                                summary.plans_skipped)
            if config.eval_dir is not None:
                summary.messages["/eval/*"] = _log_eval(Path(config.eval_dir), first, channels, context)
        finally:
            writer.close()
    summary.seconds = time.perf_counter() - t0
    summary.bytes = output.stat().st_size
    return summary


def open_inputs(workspace: Path, output: Path, suffix: str, config: FoxgloveConfig) -> Any:
    """The workspace's frames store, after checking the config and the output's suffix."""
    from mapkit.ingest import open_frames_store

    config.validate()
    if output.suffix != suffix:
        raise ExchangeError(f"-o {output}: give a file name ending in {suffix}")
    frames = open_frames_store(workspace)
    if len(frames.stamp_ns) == 0:
        raise ExchangeError(f"{workspace}/frames.zarr has no frames; nothing to export")
    return frames


def missing_layers(workspace: Path) -> list[str]:
    """A note per map layer the workspace lacks (the export writes what exists)."""
    from mapkit.esdf import MAP
    from mapkit.fusion import CLOUD

    notes = []
    if not (workspace / CLOUD).exists():
        notes.append(f"no {CLOUD}: the cloud is left out (make it with `mapkit fuse -w {workspace}`)")
    if not (workspace / MAP).exists():
        notes.append(f"no {MAP}: the ESDF is left out (make it with `mapkit esdf -w {workspace}`)")
    return notes
