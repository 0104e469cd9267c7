"""`mapkit export` on a simulated flight: goals in observed free space, body frame, contiguous split."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest
import zarr
from click.testing import CliRunner

from mapkit.cli.main import main
from mapkit.esdf import EsdfConfig, build_esdf
from mapkit.export import FUTURE, HIDDEN, RANDOM, ExportConfig, ExportError, export_tuples, split_segments
from mapkit.fusion import FuseConfig, fuse
from mapkit.sim import SimConfig, World, simulate


@pytest.fixture(scope="module")
def workspace(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, World]:
    tmp = tmp_path_factory.mktemp("export")
    result = simulate(SimConfig(world="forest", seed=2, duration=8.0, width=96, height=72), tmp / "flight", progress=False)
    ws = tmp / "ws"
    fuse([result.bag_path], ws, FuseConfig(voxel=0.1), progress=False)
    build_esdf(ws, EsdfConfig(voxel=0.2, sigma=0.0), progress=False)
    return ws, result.world


def test_goals_split_and_store(workspace: tuple[Path, World]) -> None:
    ws, world = workspace
    config = ExportConfig(goals_per_frame=4, clearance=0.3, seed=1)
    s = export_tuples(ws, config, progress=False)
    root = zarr.open_group(ws / "tuples.zarr", mode="r")
    n = s.frames
    assert n > 100 and s.train + s.val == n and s.val > 0 and s.train > s.val
    goals = root["goals_body"][:]
    assert goals.shape == (n, 4, 3) and root["depth"].shape[0] == n
    T_wb = root["T_world_body"][:]
    world_goals = np.einsum("nij,ngj->ngi", T_wb[:, :3, :3], goals) + T_wb[:, None, :3, 3]
    # Every goal keeps the clearance from the true world (up to map resolution).
    d = world.signed_distance(world_goals.reshape(-1, 3))
    assert d.min() > 0.3 - 0.2
    kinds = root["goal_kind"][:]
    assert set(np.unique(kinds)) <= {FUTURE, RANDOM, HIDDEN} and (kinds == FUTURE).any() and (kinds == RANDOM).any()
    # Random goals lie in the camera's field of view.
    T_wc = root["T_world_camera"][:]
    K = np.asarray(root.attrs["K"])
    rnd = kinds == RANDOM
    cam = np.einsum("nji,ngj->ngi", T_wc[:, :3, :3], world_goals - T_wc[:, None, :3, 3])[rnd]
    assert (cam[:, 2] > 0).all()
    u = K[0, 0] * cam[:, 0] / cam[:, 2] + K[0, 2]
    assert (u > -1).all() and (u < root.attrs["width"]).all()
    # Future goals are positions the flight reached later.
    fut = kinds == FUTURE
    frames = zarr.open_group(ws / "frames.zarr", mode="r")
    flight = frames["T_world_body"][:, :3, 3]
    dist = np.linalg.norm(world_goals[fut][:, None, :] - flight[None], axis=2).min(axis=1)
    assert dist.max() < 1e-4
    # The split is contiguous: few switches between train and val along time.
    split = root["split"][:]
    assert np.count_nonzero(np.diff(split.astype(int))) <= 2 * s.val / 20 + 2
    attrs = dict(root.attrs)
    assert attrs["kind"] == "mapkit.tuples" and len(attrs["map"]["sha256"]) == 64
    assert json.loads(json.dumps(attrs["parameters"]))["goals_per_frame"] == 4
    np.testing.assert_allclose(root["velocity_body"][:].mean(axis=0)[0] > 0, True)  # flying forward


def test_split_is_seeded_and_by_segment() -> None:
    stamps = (np.arange(300) * 1e9 / 30).astype(np.int64)
    src = np.zeros(300, np.int32)
    config = ExportConfig(segment_seconds=1.0, val_fraction=0.3, seed=4)
    a, b = split_segments(stamps, src, config), split_segments(stamps, src, config)
    np.testing.assert_array_equal(a, b)
    seg = (np.arange(300) // 30)
    for k in range(10):  # each one-second segment is all train or all val
        assert len(set(a[seg == k])) == 1
    assert 2 <= a.reshape(10, 30)[:, 0].sum() <= 4


def test_export_bad_inputs(workspace: tuple[Path, World], tmp_path: Path) -> None:
    ws, _ = workspace
    with pytest.raises(ExportError, match="no valid goals"):
        export_tuples(ws, ExportConfig(clearance=50.0), overwrite=True, progress=False)
    with pytest.raises(ExportError, match=r"goal_range 5\.0 1\.0"):
        export_tuples(ws, ExportConfig(goal_range=(5.0, 1.0)), overwrite=True, progress=False)
    # Export before esdf.
    only_frames = tmp_path / "frames_only"
    only_frames.mkdir()
    shutil.copytree(ws / "frames.zarr", only_frames / "frames.zarr")
    result = CliRunner().invoke(main, ["export", "-w", str(only_frames)])
    assert result.exit_code == 1 and "mapkit esdf" in result.output and "Traceback" not in result.output
    # A map in another frame than the frames.
    other = tmp_path / "other"
    shutil.copytree(ws, other, ignore=shutil.ignore_patterns("tuples.zarr"))
    meta = other / "map.zarr" / "zarr.json"
    text = meta.read_text().replace('"frame_id": "world"', '"frame_id": "map"')
    meta.write_text(text)
    with pytest.raises(ExportError, match=r"map.zarr is in frame 'map' but frames.zarr in 'world'"):
        export_tuples(other, progress=False)
