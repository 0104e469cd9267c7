"""TSDF fusion against analytic scenes (box and sphere over a floor) recorded as real MCAP flights."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import open3d as o3d
import pytest
from click.testing import CliRunner
from scenes import box_world, orbit_poses, record_scene, sphere_world

from mapkit.cli.main import main
from mapkit.fusion import FuseConfig, FusionError, estimate_blocks, fuse
from mapkit.ingest import open_frames_store


@pytest.fixture(scope="module")
def box_flight(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return record_scene(box_world(), tmp_path_factory.mktemp("box") / "box.mcap", orbit_poses(36))


@pytest.fixture(scope="module")
def sphere_flight(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return record_scene(sphere_world(), tmp_path_factory.mktemp("sphere") / "sphere.mcap", orbit_poses(36, target=(0, 0, 1.2)))


@pytest.mark.parametrize("scene", ["box", "sphere"])
def test_fused_cloud_lies_on_the_true_surface(tmp_path: Path, scene: str, box_flight: Path, sphere_flight: Path) -> None:
    flight, world = (box_flight, box_world()) if scene == "box" else (sphere_flight, sphere_world())
    summary = fuse([flight], tmp_path, FuseConfig(voxel=0.05), progress=False)
    cloud = o3d.io.read_point_cloud(str(tmp_path / "cloud.ply"))
    points = np.asarray(cloud.points)
    assert len(points) == summary.points > 1000 and cloud.has_normals()
    error = np.abs(world.signed_distance(points))
    assert error.mean() <= 0.25 * 0.05, error.mean()  # issue bar: ≤ 0.25 TSDF voxel
    # Normals point away from the surface (into free space).
    normals = np.asarray(cloud.normals)
    eps = 0.02
    outward = world.signed_distance(points + eps * normals) > world.signed_distance(points - eps * normals)
    assert outward.mean() > 0.95
    assert (tmp_path / "cloud.ply").read_bytes()[:200].find(b"binary_little_endian") > 0
    assert summary.frames_used == 36 and summary.blocks > 0


def test_block_estimate_is_sized_from_the_data(tmp_path: Path, box_flight: Path) -> None:
    summary = fuse([box_flight], tmp_path, FuseConfig(voxel=0.05), progress=False)
    estimate = estimate_blocks(open_frames_store(tmp_path), FuseConfig(voxel=0.05))
    assert summary.blocks <= estimate <= 3 * summary.blocks + 256
    finer = estimate_blocks(open_frames_store(tmp_path), FuseConfig(voxel=0.025))
    assert finer > 2 * estimate  # surface blocks grow ~4x when the voxel halves


def test_reuses_up_to_date_frames_and_mesh(tmp_path: Path, box_flight: Path) -> None:
    fuse([box_flight], tmp_path, FuseConfig(voxel=0.1), progress=False)
    stamp = (tmp_path / "frames.zarr" / "zarr.json").stat().st_mtime_ns
    with pytest.raises(Exception, match="--overwrite"):
        fuse([box_flight], tmp_path, FuseConfig(voxel=0.1), progress=False)
    fuse([box_flight], tmp_path, FuseConfig(voxel=0.1, mesh=True), overwrite=True, progress=False)
    assert (tmp_path / "frames.zarr" / "zarr.json").stat().st_mtime_ns == stamp  # not re-ingested
    mesh = o3d.io.read_triangle_mesh(str(tmp_path / "mesh.ply"))
    assert len(mesh.triangles) > 100


def run(*args: object) -> tuple[int, str]:
    result = CliRunner().invoke(main, [str(a) for a in args], catch_exceptions=False)
    return result.exit_code, result.output


def test_cli_fuse_and_bad_inputs(tmp_path: Path, box_flight: Path) -> None:
    ws = tmp_path / "ws"
    code, out = run("fuse", box_flight, "-w", ws, "--voxel", "0")
    assert code == 2 and "--voxel 0.0 must be positive" in out and "Traceback" not in out  # a usage error
    code, out = run("fuse", box_flight, "-w", ws, "--device", "cuda:99")
    assert code == 1 and ("cuda" in out.lower()) and "Traceback" not in out
    assert not ws.exists() or not any(ws.iterdir())  # refused before ingesting anything
    code, out = run("fuse", "-w", tmp_path / "empty")
    assert code == 1 and "run `mapkit ingest` first" in out
    code, out = run("esdf", "-w", tmp_path / "empty")
    assert code == 1 and "run `mapkit fuse" in out
    code, out = run("fuse", box_flight, "-w", ws, "--voxel", "0.1")
    assert code == 0 and "fused 36 of 36 frames" in out and "frames/s" in out, out
    # the summary names every file it wrote: the store it ingested, the fused files and their manifest
    assert f"wrote {ws}/frames.zarr, {ws}/cloud.ply, {ws}/tsdf.npz, {ws}/fuse.json\n" in out, out
    code, out = run("fuse", "-w", ws, "--voxel", "0.1", "--mesh", "--overwrite")
    assert code == 0 and f"wrote {ws}/cloud.ply, {ws}/tsdf.npz, {ws}/mesh.ply, {ws}/fuse.json\n" in out, out


def test_no_depth_in_range_is_an_error(tmp_path: Path, box_flight: Path) -> None:
    with pytest.raises(FusionError, match=r"depth within max_depth 0.3 m is needed"):
        fuse([box_flight], tmp_path, FuseConfig(voxel=0.05, max_depth=0.3), progress=False)
    assert not (tmp_path / "cloud.ply").exists()


def test_no_surface_left_is_one_line_and_the_old_cloud_stays(tmp_path: Path, box_flight: Path) -> None:
    fuse([box_flight], tmp_path, FuseConfig(voxel=0.1), progress=False)
    before = (tmp_path / "cloud.ply").read_bytes()
    code, out = run("fuse", "-w", tmp_path, "--voxel", "1e6", "--overwrite")
    assert code == 1 and "empty cloud" in out and "--voxel 1000000.0" in out and "Traceback" not in out
    assert len([line for line in out.splitlines() if line.startswith("error:")]) == 1
    assert (tmp_path / "cloud.ply").read_bytes() == before


def test_one_pixel_images_are_one_line(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    import recordings

    monkeypatch.setattr(recordings, "W", 1)
    monkeypatch.setattr(recordings, "H", 1)
    rec = recordings.write_recording(tmp_path / "px", depth_fn=lambda i: np.full((1, 1), 2.0, np.float32))
    code, out = run("fuse", rec.path, "-w", tmp_path / "ws")
    assert code == 1 and "no frame touches the map" in out and "1x1" in out and "Traceback" not in out
    assert not (tmp_path / "ws" / "cloud.ply").exists()


def test_fuse_outputs_are_one_unit(tmp_path: Path, box_flight: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """A writer that fails (or writes short on a full disk) keeps every old output; a workspace whose
    outputs no longer match fuse.json (a fuse killed while replacing them) is refused by esdf."""
    fuse([box_flight], tmp_path, FuseConfig(voxel=0.1, mesh=True), progress=False)
    names = ("cloud.ply", "mesh.ply", "tsdf.npz", "fuse.json")
    before = {n: (tmp_path / n).read_bytes() for n in names}

    def short_write(path: str, mesh, **kw) -> bool:
        Path(path).write_bytes(b"ply\n")  # what a full disk leaves
        return False

    monkeypatch.setattr(o3d.io, "write_triangle_mesh", short_write)
    with pytest.raises(FusionError, match="could not write the mesh completely"):
        fuse([], tmp_path, FuseConfig(voxel=0.08, mesh=True), overwrite=True, progress=False)
    monkeypatch.undo()
    assert {n: (tmp_path / n).read_bytes() for n in names} == before
    assert not [p.name for p in tmp_path.iterdir() if ".partial-" in p.name]

    (tmp_path / "tsdf.npz").write_bytes(before["tsdf.npz"][: len(before["tsdf.npz"]) // 2])
    code, out = run("esdf", "-w", tmp_path)
    assert code == 1 and "tsdf.npz is not the file fuse.json describes" in out and "--overwrite" in out
    (tmp_path / "fuse.json").unlink()
    code, out = run("esdf", "-w", tmp_path)
    assert code == 1 and "no complete fused map" in out and "Traceback" not in out


@pytest.mark.slow
def test_fuse_then_esdf_as_typed_in_a_fresh_directory(tmp_path: Path, box_flight: Path,
                                                      monkeypatch: pytest.MonkeyPatch) -> None:
    """`mapkit fuse flight.mcap` then `mapkit esdf --voxel 0.1`: no -w, the current directory."""
    import shutil

    shutil.copy(box_flight, tmp_path / "flight.mcap")
    monkeypatch.chdir(tmp_path)
    code, out = run("fuse", "flight.mcap")
    assert code == 0 and f"workspace: {tmp_path}" in out and (tmp_path / "cloud.ply").exists(), out
    code, out = run("esdf", "--voxel", "0.1")
    assert code == 0 and "wrote map.zarr" in out and (tmp_path / "map.zarr").is_dir(), out
