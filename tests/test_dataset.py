"""`mapkit dataset`: deterministic varied worlds, a resumable build into normal workspaces, world-level
splits, and the estimate that refuses a dataset the disk cannot hold."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from click.testing import CliRunner

from mapkit.cli.main import main
from mapkit.dataset import (
    DONE,
    CameraVariant,
    DatasetConfig,
    DatasetError,
    build_dataset,
    dataset_workspaces,
    parse_cameras,
    split_worlds,
    world_specs,
)
from mapkit.export import ExportConfig


def small(**kw: object) -> DatasetConfig:
    base = dict(worlds=2, kinds=("forest", "office"), seed=500, duration=4.0, rate=3.0, workers=1,
                export=ExportConfig(goals_per_frame=3, goal_mix=(0.0, 0.5, 0.5)))
    return DatasetConfig(**{**base, **kw})  # type: ignore[arg-type]  # a dict of mixed field values


def test_world_specs_are_varied_and_deterministic() -> None:
    config = DatasetConfig(worlds=12)
    a, b = world_specs(config), world_specs(config)
    assert a == b
    assert [s.kind for s in a[:3]] == ["forest", "office", "garage"]
    assert a[0].tilt_deg == 0.0 and (a[0].width, a[0].height) == (160, 120)  # evaluation renders world 0's camera
    assert len({s.seed for s in a}) == 12 and len({s.tilt_deg for s in a}) > 6 and len({s.speed for s in a}) > 6
    assert {s.noise for s in a} == {"none", "realsense"}
    # Growing the dataset keeps the worlds already made.
    assert world_specs(DatasetConfig(worlds=20))[:12] == a


@pytest.mark.slow
def test_build_resume_and_split(tmp_path: Path) -> None:
    root = tmp_path / "ds"
    s = build_dataset(root, small(), progress=False)
    assert sorted(s.done) == [w.name for w in world_specs(small())] and not s.failed
    for ws in dataset_workspaces(root):
        for store in ("frames.zarr", "map.zarr", "tuples.zarr", DONE):
            assert (ws / store).exists(), (ws, store)
        item = json.loads((ws / DONE).read_text())
        assert item["tuples"] > 0 and "hidden" in item["export"]["kinds"]
        assert (ws / "recording" / "flight.world.json").exists()
    again = build_dataset(root, small(), progress=False)
    assert again.done == [] and len(again.skipped) == 2
    train_ws, val_ws = split_worlds(root, 1)
    assert not set(train_ws) & set(val_ws) and len(val_ws) == 1 and train_ws[0].name.startswith("000-")
    with pytest.raises(DatasetError, match="--val-worlds 2"):
        split_worlds(root, 2)


@pytest.mark.slow
def test_bad_requests_are_one_line_errors(tmp_path: Path) -> None:
    with pytest.raises(DatasetError, match="GB free"):
        build_dataset(tmp_path / "huge", DatasetConfig(worlds=200000), progress=False, dry_run=True)
    with pytest.raises(DatasetError, match="kinds moon"):
        build_dataset(tmp_path / "k", small(kinds=("moon",)), progress=False)
    with pytest.raises(DatasetError, match="tilt_deg"):
        build_dataset(tmp_path / "t", small(tilt_deg=(0.0, float("nan"))), progress=False)
    result = CliRunner().invoke(main, ["dataset", "-o", str(tmp_path / "d"), "--worlds", "0"])
    assert result.exit_code == 2 and "'--worlds': 0 must be >= 1" in result.output and "Traceback" not in result.output
    with pytest.raises(DatasetError, match=r"holds no dataset.json"):
        dataset_workspaces(tmp_path)


def test_cli_ranges_reach_the_worlds(tmp_path: Path) -> None:
    args = ["dataset", "-o", str(tmp_path / "d"), "--worlds", "3", "--set", "kinds=office", "--dry-run"]
    default = CliRunner().invoke(main, args)
    assert default.exit_code == 0, default.output
    # the CLI's defaults are the library's: the same worlds either way
    for spec in world_specs(DatasetConfig(worlds=3, kinds=("office",))):
        assert (f"{spec.name}: {spec.size[0]}x{spec.size[1]}x{spec.size[2]} m, density {spec.density}, {spec.speed} m/s, "
                f"camera {spec.width}x{spec.height} fx {spec.fx} tilt {spec.tilt_deg} deg, noise {spec.noise}") in default.output
    result = CliRunner().invoke(main, args + ["--set", "density_scale=[2, 2]", "--set", "speed=1.2,1.2", "--set",
                                              "size_scale=0.5,0.5", "--set", "tilt_deg=5,5", "--set", "noise_fraction=0"])
    assert result.exit_code == 0, result.output
    lines = [line for line in result.output.splitlines() if "-office-" in line]
    assert len(lines) == 3 and all("density 0.1, 1.2 m/s" in line and "noise none" in line for line in lines)
    assert "tilt 0.0 deg" in lines[0] and all("tilt 5.0 deg" in line for line in lines[1:])  # world 0 flies level
    bad = CliRunner().invoke(main, args + ["--set", "speed=0.5,2"])
    assert bad.exit_code == 2 and bad.output.strip() == ("error: main dataset: speed 0.5 2.0: need 1.0 <= min <= max <= 3.0 "
                                                         "(see main dataset --help)")  # a usage error


def test_cameras_option_sets_every_worlds_camera(tmp_path: Path) -> None:
    """`--set cameras=640x360` (the paper preset's D435) flies every world with it, at the D435's focal
    length; the default string is the library's default; malformed or absurd cameras are one line."""
    assert parse_cameras("160x120,212x120:1.1,192x144:0.9") == DatasetConfig().cameras
    assert parse_cameras(" 640X360 ") == (CameraVariant(640, 360, 1.0),)
    args = ["dataset", "-o", str(tmp_path / "d"), "--worlds", "4", "--dry-run"]
    paper = CliRunner().invoke(main, args + ["--set", "cameras=640x360"])
    assert paper.exit_code == 0, paper.output
    lines = [line for line in paper.output.splitlines() if " m/s, camera " in line]
    assert len(lines) == 4 and all("camera 640x360 fx 387.0 " in line for line in lines)
    for text, message in (("640by360", "is not WIDTHxHEIGHT[:FX_SCALE]"), (",", "names no camera"),
                          ("8x8", "need 16..4096 pixels a side"), ("640x360:9", "focal-length scale in 0.25..4")):
        bad = CliRunner().invoke(main, args + ["--set", f"cameras={text}"])
        assert bad.exit_code == 2 and message in bad.output and len(bad.output.strip().splitlines()) == 1, bad.output
