"""Export's goal mix on a synthetic world with a wall: fractions as configured, hidden goals really
hidden (the straight line is blocked in the map and in the exact world)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import zarr
from scenes import record_scene

from mapkit.esdf import EsdfConfig, EsdfMap, build_esdf
from mapkit.export import FUTURE, HIDDEN, RANDOM, ExportConfig, ExportError, blocked_lines, export_tuples
from mapkit.fusion import FuseConfig, fuse
from mapkit.sim import Box, HalfSpace, World


def wall_world() -> World:
    """A 4 m wide, 2.5 m high wall across x = 3 (0.2 m thick) on a floor."""
    prims = [HalfSpace((0.0, 0.0, 1.0), 0.0), Box((3.0, 0.0, 1.25), (0.1, 2.0, 1.25))]
    return World(prims, np.array([[-2.0, -5.0, 0.0], [8.0, 5.0, 3.0]]), kind="wall", seed=0)


def poses_around_the_wall(n: int) -> list[np.ndarray]:
    """Level body poses (FLU) on a 3.5 m circle around the wall's centre at height 1.2 m, each facing
    the centre: the map sees both faces, so space behind the wall from any pose is observed."""
    out = []
    for a in np.linspace(0.0, 2 * np.pi, n, endpoint=False):
        p = np.array([3.0 - 3.5 * np.cos(a), 3.5 * np.sin(a), 1.2])
        yaw = np.arctan2(-p[1], 3.0 - p[0])
        T = np.eye(4)
        T[:3, :3] = [[np.cos(yaw), -np.sin(yaw), 0.0], [np.sin(yaw), np.cos(yaw), 0.0], [0.0, 0.0, 1.0]]
        T[:3, 3] = p
        out.append(T)
    return out


@pytest.fixture(scope="module")
def wall_workspace(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, World]:
    tmp = tmp_path_factory.mktemp("wall")
    world = wall_world()
    bag = record_scene(world, tmp / "wall", poses_around_the_wall(32), width=96, height=72)
    ws = tmp / "ws"
    fuse([bag], ws, FuseConfig(voxel=0.05), progress=False)
    build_esdf(ws, EsdfConfig(voxel=0.1, sigma=0.1, padding=2.5), progress=False)
    return ws, world


def test_mix_fractions_and_hidden_goals_really_hidden(wall_workspace: tuple[Path, World]) -> None:
    ws, world = wall_workspace
    config = ExportConfig(goals_per_frame=10, goal_mix=(0.0, 0.4, 0.6), goal_range=(1.5, 6.0), clearance=0.3,
                          hidden_bearing_deg=40.0, seed=3)
    s = export_tuples(ws, config, overwrite=True, progress=False)
    root = zarr.open_group(ws / "tuples.zarr", mode="r")
    kinds = root["goal_kind"][:]
    assert kinds.shape == (s.frames, 10)
    assert s.kind_counts["future_pose"] == 0 and not (kinds == FUTURE).any()
    # The configured shares: 6 of 10 goals hidden where the map has room for them, the rest visible.
    assert s.frames >= 12
    assert (kinds == HIDDEN).mean() == pytest.approx(0.6, abs=0.05) and (kinds == HIDDEN).sum(axis=1).max() == 6
    assert ((kinds == HIDDEN) | (kinds == RANDOM)).all()
    T_wb = root["T_world_body"][:]
    goals = root["goals_body"][:]
    world_goals = np.einsum("nij,ngj->ngi", T_wb[:, :3, :3], goals) + T_wb[:, None, :3, 3]
    hidden = world_goals[kinds == HIDDEN]
    starts = np.broadcast_to(T_wb[:, None, :3, 3], world_goals.shape)[kinds == HIDDEN]
    # Really hidden: in the exact world the straight line passes closer than the robot radius (0.3 m)
    # to the wall (up to the map's 0.1 m voxels), and for most the ray hits the wall itself.
    frac = np.linspace(0.0, 1.0, 200)
    lines = starts[:, None] + frac[None, :, None] * (hidden - starts)[:, None]
    closest = world.signed_distance(lines.reshape(-1, 3)).reshape(len(hidden), -1).min(axis=1)
    assert (closest < 0.3 + 0.1).all()
    t_hit = np.array([world.raycast(a, (g - a)[None])[0] for a, g in zip(starts, hidden, strict=True)])
    assert (t_hit < 1.0).mean() > 0.6
    # On the far side of the wall from the body, and free with clearance in the exact world.
    assert (np.sign(hidden[:, 0] - 3.0) != np.sign(starts[:, 0] - 3.0)).mean() > 0.95
    assert world.signed_distance(hidden).min() > 0.3 - 0.1
    blocked = root["goal_blocked"][:].astype(bool)
    assert blocked[kinds == HIDDEN].all()
    assert s.blocked_fraction == pytest.approx(blocked.mean())
    assert sum(s.distance_histogram.values()) == kinds.size
    assert "hidden" in s.mix_text()


def test_blocked_lines_against_the_wall(wall_workspace: tuple[Path, World]) -> None:
    ws, _ = wall_workspace
    esdf = EsdfMap.open(ws / "map.zarr")
    start = np.array([-0.5, 0.0, 1.2])
    goals = np.array([[5.0, 0.0, 1.2], [5.0, 0.5, 1.2], [2.0, 0.0, 1.2], [0.0, 3.5, 1.2]])
    np.testing.assert_array_equal(blocked_lines(start, goals, esdf, threshold=0.3), [True, True, False, False])


def test_goal_mix_is_validated(wall_workspace: tuple[Path, World]) -> None:
    ws, _ = wall_workspace
    for mix in ((0.0, 0.0, 0.0), (-1.0, 1.0, 1.0), (float("nan"), 1.0, 1.0)):
        with pytest.raises(ExportError, match="goal_mix"):
            export_tuples(ws, ExportConfig(goal_mix=mix), overwrite=True, progress=False)
