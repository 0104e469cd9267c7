"""`mapkit export-rerun`: the same layers as the Foxglove export, as ``rerun-sdk`` archetypes in a Rerun
recording (.rrd) on the timeline ``recording``, with a default blueprint; entities in docs/exchange.md."""

from __future__ import annotations

import time
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from mapkit.exchange._foxglove import (
    PLAN_CORRIDOR,
    ExchangeError,
    ExportSummary,
    FoxgloveConfig,
    _height_colours,
    _plan_results,
    missing_layers,
    open_inputs,
    read_eval_paths,
)
from mapkit.geometry import invert_transform, quat_xyzw_from_matrix

RerunConfig = FoxgloveConfig
"""The same choices as the Foxglove export (model, eval folder, plan frames); ``voxel_limit`` and
``slice_heights`` do not apply (a Tensor holds any size)."""

TIMELINE = "recording"


@dataclass
class RerunSummary(ExportSummary):
    """What was written to the .rrd."""

    frames: int = 0
    plans: int = 0
    eval_paths: int = 0
    entities: list[str] = field(default_factory=list)


def _transform(T: NDArray[np.float64]) -> Any:
    import rerun as rr

    return rr.Transform3D(translation=T[:3, 3], quaternion=rr.Quaternion(xyzw=quat_xyzw_from_matrix(T[:3, :3])))


def _at(rec: Any, ns: int) -> None:
    rec.set_time(TIMELINE, timestamp=np.datetime64(int(ns), "ns"))


def _log_flight(rec: Any, frames: Any) -> int:
    import rerun as rr

    height, width = frames.depth.shape[1:]
    rec.log("/world/body/camera", rr.Pinhole(image_from_camera=np.asarray(frames.K), resolution=[width, height]), static=True)
    for i, ns in enumerate(frames.stamp_ns.tolist()):
        _at(rec, ns)
        T_wb = frames.T_world_body[i]
        rec.log("/world/body", _transform(T_wb))
        rec.log("/world/body/camera", _transform(invert_transform(T_wb) @ frames.T_world_camera[i]))
        rec.log("/world/body/camera/depth", rr.DepthImage(np.asarray(frames.depth[i], dtype=np.float32), meter=1.0))
    return len(frames.stamp_ns)


def _log_maps(rec: Any, workspace: Path, frames: Any) -> list[str]:
    import open3d as o3d
    import rerun as rr

    from mapkit.esdf import MAP, EsdfMap
    from mapkit.fusion import CLOUD

    logged = []
    if (workspace / CLOUD).exists():
        points = np.asarray(o3d.io.read_point_cloud(workspace / CLOUD).points)
        rec.log("/world/cloud", rr.Points3D(points, colors=_height_colours(points[:, 2])), static=True)
        logged.append("/world/cloud")
    if (workspace / MAP).exists():
        esdf = EsdfMap.open(workspace / MAP)
        grid = esdf.read("esdf", ...)
        rec.log("/map/esdf", rr.Tensor(grid, dim_names=["x", "y", "z"]), static=True)
        k = int(np.clip(round((np.median(frames.T_world_body[:, 2, 3]) - esdf.origin[2]) / esdf.voxel_size), 0, esdf.shape[2] - 1))
        i, j = np.meshgrid(np.arange(esdf.shape[0]), np.arange(esdf.shape[1]), indexing="ij")
        centres = np.asarray(esdf.origin) + esdf.voxel_size * np.stack([i.ravel(), j.ravel(), np.full(i.size, k)], axis=1)
        d = grid[:, :, k].ravel()
        u = np.clip((np.nan_to_num(d, nan=0.0) + 1.0) / 2.0, 0.0, 1.0)  # −1 m red … +1 m blue
        colours = np.stack([255 * (1 - u), 80 * np.ones_like(u), 255 * u], axis=1).astype(np.uint8)
        rec.log("/world/esdf_slice", rr.Points3D(centres, colors=colours, radii=0.3 * esdf.voxel_size), static=True)
        logged += ["/map/esdf", "/world/esdf_slice"]
    return logged


def _log_plans(rec: Any, frames: Any, config: RerunConfig, skipped: Counter[str]) -> int:
    import rerun as rr

    count = 0
    for ns, T_wb, result in _plan_results(frames, config, skipped):
        _at(rec, ns)
        R, p = T_wb[:3, :3], T_wb[:3, 3]
        ends = np.concatenate([np.zeros((1, 3)), result.keypoints])
        lo = np.minimum(ends[:-1], ends[1:]) - PLAN_CORRIDOR
        hi = np.maximum(ends[:-1], ends[1:]) + PLAN_CORRIDOR
        quaternion = rr.Quaternion(xyzw=quat_xyzw_from_matrix(R))
        rec.log("/world/plans/trajectory", rr.LineStrips3D([result.samples_body @ R.T + p],
                                                           colors=[(30, 200, 60)] if result.execute else [(230, 30, 30)]))
        rec.log("/world/plans/keypoints", rr.Points3D(result.keypoints @ R.T + p, radii=0.08, colors=[(255, 150, 0)]))
        rec.log("/world/plans/corridor", rr.Boxes3D(centers=(0.5 * (lo + hi)) @ R.T + p, half_sizes=0.5 * (hi - lo),
                                                    quaternions=[quaternion] * len(lo), colors=[(50, 150, 255, 40)]))
        count += 1
    return count


def _log_eval(rec: Any, eval_dir: Path) -> int:
    import rerun as rr

    paths = read_eval_paths(eval_dir)
    groups: dict[tuple[str, str], list[tuple[NDArray[np.float64], tuple[int, ...]]]] = {}
    for world, method, points, colour in paths:
        groups.setdefault((world, method), []).append((points, tuple(int(255 * c) for c in colour)))
    for (world, method), strips in sorted(groups.items()):
        rec.log(f"/eval/{world}/{method}", rr.LineStrips3D([s for s, _ in strips], colors=[c for _, c in strips]), static=True)
    return len(paths)


def _blueprint() -> Any:
    import rerun.blueprint as rrb

    return rrb.Blueprint(rrb.Horizontal(
        rrb.Spatial3DView(name="world", origin="/world"),
        rrb.Vertical(rrb.Spatial2DView(name="depth", origin="/world/body/camera"),
                     rrb.TensorView(name="ESDF", origin="/map/esdf")),
        column_shares=[3, 2]))


def export_rerun(workspace: str | Path, output: str | Path, config: RerunConfig = RerunConfig()) -> RerunSummary:  # noqa: B008 - a frozen dataclass
    """Write the workspace's flight, cloud, ESDF (and plans, evaluation paths) to ``output`` (.rrd),
    atomically; see the module docstring for the entities."""
    import rerun as rr

    from mapkit.workspace import atomic_output

    t0 = time.perf_counter()
    workspace, output = Path(workspace), Path(output)
    frames = open_inputs(workspace, output, ".rrd", config)
    summary = RerunSummary(output)
    with atomic_output(output, overwrite=config.overwrite) as tmp:
        rec = rr.RecordingStream("mapkit")
        rec.save(str(tmp), default_blueprint=_blueprint())
        try:
            summary.frames = _log_flight(rec, frames)
            summary.entities = ["/world/body", "/world/body/camera", "/world/body/camera/depth", *_log_maps(rec, workspace, frames)]
            if config.model is not None:
                summary.plans = _log_plans(rec, frames, config, summary.plans_skipped)
            if config.eval_dir is not None:
                summary.eval_paths = _log_eval(rec, Path(config.eval_dir))
        finally:
            rec.flush()
            rec.disconnect()
    summary.notes = missing_layers(workspace)
    summary.seconds = time.perf_counter() - t0
    summary.bytes = output.stat().st_size
    return summary


def open_in_rerun(path: Path) -> None:
    """Start the Rerun viewer (the ``rerun`` program installed with rerun-sdk) on ``path``, detached."""
    import shutil
    import subprocess
    import sys

    viewer = shutil.which("rerun") or str(Path(sys.executable).with_name("rerun"))
    if not Path(viewer).exists():
        raise ExchangeError("the Rerun viewer (`rerun`) is not installed; install rerun-sdk, or open the file later")
    subprocess.Popen([viewer, str(path)], start_new_session=True, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
