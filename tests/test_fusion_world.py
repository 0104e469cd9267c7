"""`mapkit fuse-world`: many flights fused tile by tile equal the single-process fuse + esdf, array for array."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner
from scenes import box_world, orbit_poses, record_scene

import mapkit.esdf._world as world_esdf
from mapkit.cli.main import main
from mapkit.esdf import EsdfConfig, EsdfMap, build_esdf
from mapkit.fusion import FuseConfig, FusionError, WorldConfig, fuse, fuse_world, open_world
from mapkit.fusion._occupancy import Grid, carve_free_space, occupancy_from_tsdf
from mapkit.ingest import open_frames_store


@pytest.fixture(scope="module")
def two_flights(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """One workspace holding two flights over the same world (a low and a high orbit), fused."""
    tmp = tmp_path_factory.mktemp("world")
    low = record_scene(box_world(), tmp / "low.mcap", orbit_poses(14, radius=2.5, height=1.0))
    high = record_scene(box_world(), tmp / "high.mcap", orbit_poses(14, radius=3.5, height=2.2))
    fuse([low, high], tmp / "ws", FuseConfig(voxel=0.05), progress=False)
    return tmp / "ws"


def _single_process(ws: Path, config: WorldConfig) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(tsdf, observed, behind) as `mapkit esdf` computes them from the whole fused TSDF and all frames."""
    meta = json.loads((ws / "fuse.json").read_text())
    lo, hi = (np.asarray(b) for b in meta["bounds"])
    grid = Grid.covering(lo - config.padding, hi + config.padding, config.voxel)
    _, tsdf = occupancy_from_tsdf(ws / "tsdf.npz", grid, tsdf_voxel=config.fuse.voxel, trunc_voxels=config.fuse.trunc)
    observed, behind = ~np.isnan(tsdf), np.zeros(grid.shape, dtype=bool)
    carve_free_space(open_frames_store(ws), grid, observed, max_depth=config.fuse.max_depth, behind=behind,
                     solid_depth=config.solid_depth)
    return tsdf, observed, behind


def _maps_equal(a: Path, b: Path) -> None:
    ma, mb = EsdfMap.open(a / "map.zarr"), EsdfMap.open(b / "map.zarr")
    for name in ("esdf", "esdf_raw", "observed"):
        np.testing.assert_array_equal(np.asarray(getattr(ma, name)[:]), np.asarray(getattr(mb, name)[:]), err_msg=name)


@pytest.mark.slow
def test_tiled_world_equals_the_single_process_map(two_flights: Path, tmp_path: Path) -> None:
    """Tiles (64 voxels, so 3 x 3 x 1 of them) give the single process's TSDF samples, observed and
    behind-surface grids exactly (Open3D integrates each voxel from its position and the frames alone,
    and every position is placed on the whole grid before a tile is cut out), and so the same map."""
    bounds = json.loads((two_flights / "fuse.json").read_text())["bounds"]
    config = WorldConfig(voxel=0.1, tile=64, bounds=(tuple(bounds[0]), tuple(bounds[1])), fuse=FuseConfig(voxel=0.05))
    s = fuse_world([two_flights], tmp_path / "world", config, progress=False)
    assert s.tiles == s.tiles_fused > 1 and s.frames == 28
    world = open_world(tmp_path / "world")
    tsdf, observed, behind = _single_process(two_flights, config)
    np.testing.assert_array_equal(np.asarray(world["tsdf"][:]), tsdf)
    np.testing.assert_array_equal(np.asarray(world["observed"][:]), observed)
    np.testing.assert_array_equal(np.asarray(world["behind"][:]), behind)
    for unknown in ("free", "occupied"):
        esdf_config = EsdfConfig(voxel=0.1, max_dist=0.8, unknown=unknown)
        build_esdf(two_flights, esdf_config, overwrite=True, progress=False, workers=1)
        build_esdf(tmp_path / "world", esdf_config, overwrite=True, progress=False)
        _maps_equal(two_flights, tmp_path / "world")
    assert EsdfMap.open(tmp_path / "world" / "map.zarr").attrs["parameters"]["world"] is True


@pytest.mark.slow
def test_tiles_and_world_esdf_on_a_local_cluster_equal_them_in_process(two_flights: Path, tmp_path: Path,
                                                                       monkeypatch: pytest.MonkeyPatch) -> None:
    config = WorldConfig(voxel=0.2, tile=64, fuse=FuseConfig(voxel=0.05))
    fuse_world([two_flights], tmp_path / "a", config, progress=False)
    s = fuse_world([two_flights], tmp_path / "b", config, progress=False, workers=2)
    assert s.workers == 2
    a, b = open_world(tmp_path / "a"), open_world(tmp_path / "b")
    for name in ("tsdf", "observed", "behind"):
        np.testing.assert_array_equal(np.asarray(a[name][:]), np.asarray(b[name][:]), err_msg=name)
    assert a.attrs["shape"] == b.attrs["shape"] and a.attrs["origin"] == b.attrs["origin"]
    # and the world's ESDF (the chunked pocket passes included) on the cluster equals it in process
    monkeypatch.setattr(world_esdf, "_CHUNK", 64)  # 2 x 2 x 1 chunks on this small grid
    esdf_config = EsdfConfig(voxel=0.2, max_dist=1.0, unknown="free")
    build_esdf(tmp_path / "a", esdf_config, progress=False)
    s_esdf = build_esdf(tmp_path / "b", esdf_config, progress=False, workers=2)
    assert s_esdf.chunked is not None and s_esdf.chunked.chunks == 4
    _maps_equal(tmp_path / "a", tmp_path / "b")


def test_world_config_and_inputs_are_checked(tmp_path: Path) -> None:
    with pytest.raises(FusionError, match="tile 100 must be a positive multiple of 64"):
        fuse_world([tmp_path], tmp_path / "w", WorldConfig(tile=100))
    with pytest.raises(FusionError, match="bounds"):
        fuse_world([tmp_path], tmp_path / "w", WorldConfig(bounds=((0, 0, 0), (1, -1, 1))))
    with pytest.raises(FusionError, match="no workspaces given"):
        fuse_world([], tmp_path / "w")
    with pytest.raises(FusionError, match="fuse-world"):
        open_world(tmp_path)


@pytest.mark.slow
def test_cli_fuse_world_then_esdf_and_bad_input(two_flights: Path, tmp_path: Path) -> None:
    runner = CliRunner()
    out = tmp_path / "world"
    result = runner.invoke(main, ["fuse-world", str(two_flights), "-o", str(out), "--voxel", "0.2", "--set", "tile=64"])
    assert result.exit_code == 0, result.output
    assert "tiles reached by 28 frames" in result.output and (out / "world.zarr").is_dir()
    result = runner.invoke(main, ["esdf", "-w", str(out), "--voxel", "0.2", "--set", "max_dist=1.0"])
    assert result.exit_code == 0, result.output
    assert EsdfMap.open(out / "map.zarr").shape == tuple(open_world(out).attrs["shape"])
    for args, message, code in (
        (["esdf", "-w", str(out), "--overwrite"], "--voxel 0.2", 1),  # the world's grid is fixed at fuse-world
        (["fuse-world", str(two_flights), "-o", str(out), "--set", "tile=100"], "tile 100", 2),  # a usage error
        (["fuse-world", str(tmp_path / "nowhere"), "-o", str(tmp_path / "w2")], "does not exist", 1),
    ):
        result = runner.invoke(main, args)
        assert result.exit_code == code, (args, result.output)
        assert message in result.output and "Traceback" not in result.output, result.output
