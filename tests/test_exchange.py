"""`mapkit export-foxglove`: the MCAP read back with the `mcap` reader, every channel decoded with
the Foxglove protobuf schemas it carries, and the values compared with the workspace's stores."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import open3d as o3d
import pytest
from click.testing import CliRunner
from scenes import box_world, orbit_poses, record_scene
from scipy.spatial.transform import Rotation

from mapkit.cli.main import main
from mapkit.esdf import EsdfConfig, EsdfMap, build_esdf
from mapkit.exchange import ExchangeError, FoxgloveConfig, export_foxglove
from mapkit.fusion import FuseConfig, fuse
from mapkit.geometry import invert_transform
from mapkit.ingest import open_frames_store


@pytest.fixture(scope="module")
def workspace(tmp_path_factory: pytest.TempPathFactory) -> Path:
    root = tmp_path_factory.mktemp("fox")
    flight = record_scene(box_world(), root / "box.mcap", orbit_poses(24))
    fuse([flight], root / "ws", FuseConfig(voxel=0.1), progress=False)
    build_esdf(root / "ws", EsdfConfig(voxel=0.1), progress=False)
    return root / "ws"


def _read(path: Path) -> dict[str, list[tuple[int, object]]]:
    from mcap.reader import make_reader
    from mcap_protobuf.decoder import DecoderFactory

    out: dict[str, list[tuple[int, object]]] = {}
    with open(path, "rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        for schema, channel, message, decoded in reader.iter_decoded_messages():
            assert schema.encoding == "protobuf" and schema.name.startswith("foxglove.")
            out.setdefault(channel.topic, []).append((message.log_time, decoded))
    return out


def _cells(msg, shape) -> np.ndarray:
    dtype = np.dtype([("distance", "<f4"), ("observed", "u1")])
    assert [f.name for f in msg.fields] == ["distance", "observed"] and msg.cell_stride == dtype.itemsize
    return np.frombuffer(msg.data, dtype=dtype).reshape(shape)


def test_flight_cloud_and_esdf_read_back_equal_to_the_stores(workspace: Path, tmp_path: Path) -> None:
    out = tmp_path / "ws.mcap"
    summary = export_foxglove(workspace, out, FoxgloveConfig())
    assert summary.esdf_as == "VoxelGrid"
    topics = _read(out)
    frames = open_frames_store(workspace)
    n = len(frames.stamp_ns)
    assert len(topics["/tf"]) == len(topics["/camera/depth"]) == len(topics["/camera/calibration"]) == n

    # Transforms at a known stamp, stamped with the recording's own time.
    i = n // 2
    log_time, tf = topics["/tf"][i]
    assert log_time == int(frames.stamp_ns[i])
    world_body, body_camera = tf.transforms
    assert world_body.timestamp.seconds * 10**9 + world_body.timestamp.nanos == int(frames.stamp_ns[i])
    assert (world_body.parent_frame_id, world_body.child_frame_id) == (frames.attrs["world_frame"], frames.attrs["body_frame"])
    for T, msg in ((frames.T_world_body[i], world_body), (invert_transform(frames.T_world_body[i]) @ frames.T_world_camera[i], body_camera)):
        np.testing.assert_allclose([msg.translation.x, msg.translation.y, msg.translation.z], T[:3, 3], atol=1e-9)
        q = [msg.rotation.x, msg.rotation.y, msg.rotation.z, msg.rotation.w]
        np.testing.assert_allclose(Rotation.from_quat(q).as_matrix(), T[:3, :3], atol=1e-9)

    # Depth in millimetres, 0 where invalid; the calibration's K.
    _, image = topics["/camera/depth"][i]
    mm = np.frombuffer(image.data, dtype="<u2").reshape(image.height, image.width)
    depth = np.asarray(frames.depth[i])
    np.testing.assert_array_equal(mm, np.where(np.isfinite(depth), np.round(depth * 1000), 0))
    np.testing.assert_allclose(np.reshape(topics["/camera/calibration"][i][1].K, (3, 3)), frames.K)

    # The cloud's points, float32.
    _, cloud = topics["/map/cloud"][0]
    packed = np.frombuffer(cloud.data, dtype=[("xyz", "<f4", 3), ("rgba", "u1", 4)])
    points = np.asarray(o3d.io.read_point_cloud(str(workspace / "cloud.ply")).points)
    np.testing.assert_allclose(packed["xyz"], points.astype(np.float32))

    # The ESDF: every voxel, and where the grid sits.
    esdf = EsdfMap.open(workspace / "map.zarr").load()
    _, grid = topics["/map/esdf"][0]
    nx, ny, nz = esdf.shape
    cells = _cells(grid, (nz, ny, nx))
    np.testing.assert_array_equal(cells["distance"].transpose(2, 1, 0), esdf.esdf.astype(np.float32))
    np.testing.assert_array_equal(cells["observed"].transpose(2, 1, 0), esdf.observed)
    corner = [grid.pose.position.x, grid.pose.position.y, grid.pose.position.z]
    np.testing.assert_allclose(corner, np.asarray(esdf.origin) - 0.5 * esdf.voxel_size)
    assert grid.cell_size.x == esdf.voxel_size and (grid.row_count, grid.column_count) == (ny, nx)


def test_a_large_esdf_becomes_slices_and_plans_and_eval_paths_are_scene_updates(workspace: Path, tmp_path: Path) -> None:
    esdf = EsdfMap.open(workspace / "map.zarr").load()
    z = float(esdf.origin[2] + 7 * esdf.voxel_size)
    evald = tmp_path / "eval"
    evald.mkdir()
    path = np.array([[0.0, 0.0, 0.0, 1.0], [1.0, 1.0, 0.0, 1.0], [2.0, 2.0, 1.0, 1.0]])
    np.savez(evald / "trajectories.npz", **{"office/000/learned": path, "office/000/straight": path[:2]})
    (evald / "results.json").write_text(json.dumps({"episodes": [
        {"world": "office", "pair": 0, "method": "learned", "outcome": "success", "start": [0, 0, 1], "goal": [2, 2, 1]},
        {"world": "office", "pair": 0, "method": "straight", "outcome": "collision", "start": [0, 0, 1],
         "goal": [2, 2, 1]}]}))
    out = tmp_path / "big.mcap"
    config = FoxgloveConfig(voxel_limit=10, slice_heights=(z,), model="pretrained", plan_count=3, goal_ahead=0.2,
                            eval_dir=evald)
    summary = export_foxglove(workspace, out, config)
    assert summary.esdf_as == "Grid slices" and summary.messages["/planner/plans"] >= 1
    assert any("more than one VoxelGrid message holds" in note for note in summary.notes)
    topics = _read(out)
    assert "/map/esdf" not in topics
    _, grid = topics["/map/esdf_slices"][0]
    nx, ny, _ = esdf.shape
    np.testing.assert_array_equal(_cells(grid, (ny, nx))["distance"].T, esdf.esdf[:, :, 7].astype(np.float32))
    assert abs(grid.pose.position.z - z) < 1e-9

    _, update = topics["/planner/plans"][0]
    entity = update.entities[0]
    assert len(entity.spheres) == len(entity.cubes) >= 1 and len(entity.lines[0].points) > 10
    _, learned = topics["/eval/learned"][0]
    line = learned.entities[0].lines[0]
    assert learned.entities[0].frame_id == "eval/office" and line.color.g > line.color.r  # success: green
    np.testing.assert_allclose([[p.x, p.y, p.z] for p in line.points], path[:, 1:4])
    assert "/eval/straight" in topics


def _eval_without_goals(tmp_path: Path) -> Path:
    """An eval folder whose results.json rows lack a key every row has."""
    evald = tmp_path / "eval_no_goal"
    evald.mkdir()
    np.savez(evald / "trajectories.npz", **{"office/000/learned": np.zeros((2, 4))})
    (evald / "results.json").write_text(json.dumps({"episodes": [
        {"world": "office", "pair": 0, "method": "learned", "outcome": "success", "start": [0, 0, 1]}]}))
    return evald


def test_the_summary_says_how_many_plans_were_written_and_why_the_others_were_not(workspace: Path,
                                                                                 tmp_path: Path) -> None:
    """More --plans than frames, and the flight's last frame with no later one to plan toward: the line
    names each reason with its count, and the counts and the plans written add up to --plans."""
    import re

    out = tmp_path / "plans.mcap"
    frames = len(open_frames_store(workspace).stamp_ns)
    r = CliRunner().invoke(main, ["export-foxglove", "-w", str(workspace), "-o", str(out), "--model", "pretrained",
                                  "--plans", str(frames + 6), "--goal-ahead", "0.5"])
    assert r.exit_code == 0, r.output
    line = next(line for line in r.output.splitlines() if line.startswith("plans: "))
    written, skipped = re.fullmatch(rf"plans: (\d+) of {frames + 6} written; skipped: (.+)", line).groups()
    assert int(written) == len(_read(out).get("/planner/plans", []))
    reasons = dict(re.fullmatch(r"(\d+) (.+)", part).group(2, 1) for part in skipped.split("; "))
    assert reasons[f"the flight has only {frames} frames"] == "6"
    assert any(reason.startswith("no frame 0.5 s later in its recording") for reason in reasons), reasons
    assert int(written) + sum(int(n) for n in reasons.values()) == frames + 6


def test_bad_requests_are_one_line(workspace: Path, tmp_path: Path) -> None:
    runner = CliRunner()
    for args, needle in ((["-o", str(tmp_path / "x.txt")], "ending in .mcap"),
                         (["-o", str(tmp_path / "x.mcap"), "--model", str(tmp_path / "none")], "--model"),
                         (["-o", str(tmp_path / "y.mcap"), "--eval", str(tmp_path)], "--eval"),
                         (["-o", str(tmp_path / "w.mcap"), "--eval", str(_eval_without_goals(tmp_path))], "KeyError: 'goal'")):
        r = runner.invoke(main, ["export-foxglove", "-w", str(workspace), *args])
        assert r.exit_code == 1 and needle in r.output and len(r.output.strip().splitlines()) == 1, r.output
    assert not (tmp_path / "x.mcap").exists() and not (tmp_path / "y.mcap").exists()
    assert runner.invoke(main, ["export-foxglove", "-w", str(workspace), "-o", str(tmp_path / "z.mcap")]).exit_code == 0
    r = runner.invoke(main, ["export-foxglove", "-w", str(workspace), "-o", str(tmp_path / "z.mcap")])
    assert r.exit_code == 1 and "--overwrite" in r.output
    with pytest.raises(ExchangeError, match="--plans 0"):
        FoxgloveConfig(plan_count=0).validate()


def _rerun_columns(path: Path, entity: str, index: str | None = "recording") -> dict[str, list]:
    """Columns of ``entity`` read back with Rerun's own reader (a local server's dataframe query)."""
    import rerun as rr

    with rr.server.Server(datasets={"export": [str(path)]}) as server:
        client = server.client()  # kept alive: the query runs in its context
        dataset = client.get_dataset("export")
        table = dataset.filter_contents(entity).reader(index=index).to_arrow_table()
    columns = table.to_pydict()
    columns["recording"] = table.column("recording").cast("int64").to_pylist()  # ns, not datetimes (µs)
    return columns


def test_rerun_recording_reads_back_equal_to_the_stores(workspace: Path, tmp_path: Path) -> None:
    from mapkit.exchange import RerunConfig, export_rerun

    evald = tmp_path / "eval"
    evald.mkdir()
    path = np.array([[0.0, 0.0, 0.0, 1.0], [1.0, 1.0, 0.0, 1.0], [2.0, 2.0, 1.0, 1.0]])
    np.savez(evald / "trajectories.npz", **{"garage/003/learned": path})
    (evald / "results.json").write_text(json.dumps({"episodes": []}))
    out = tmp_path / "ws.rrd"
    summary = export_rerun(workspace, out, RerunConfig(model="pretrained", plan_count=3, goal_ahead=0.2, eval_dir=evald))
    frames = open_frames_store(workspace)
    assert summary.frames == len(frames.stamp_ns) and summary.plans >= 1 and summary.eval_paths == 1
    assert summary.plans + sum(summary.plans_skipped.values()) == 3  # each frame asked for: a plan or a reason

    body = _rerun_columns(out, "/world/body")
    stamps = body["recording"]
    assert stamps == frames.stamp_ns.tolist()
    i = len(stamps) // 2
    np.testing.assert_allclose(body["/world/body:Transform3D:translation"][i][0], frames.T_world_body[i][:3, 3], atol=1e-6)
    q = body["/world/body:Transform3D:quaternion"][i][0]
    np.testing.assert_allclose(Rotation.from_quat(q).as_matrix(), frames.T_world_body[i][:3, :3], atol=1e-6)

    cloud = _rerun_columns(out, "/world/cloud", index=None)["/world/cloud:Points3D:positions"][0]
    points = np.asarray(o3d.io.read_point_cloud(str(workspace / "cloud.ply")).points)
    np.testing.assert_allclose(np.asarray(cloud), points, atol=1e-6)

    esdf = EsdfMap.open(workspace / "map.zarr").load()
    tensor = _rerun_columns(out, "/map/esdf", index=None)["/map/esdf:Tensor:data"][0][0]
    assert tensor["shape"] == list(esdf.shape) and [n for n in tensor["names"]] == ["x", "y", "z"]
    np.testing.assert_array_equal(np.asarray(tensor["buffer"]).reshape(esdf.shape), esdf.esdf.astype(np.float32))

    plans = _rerun_columns(out, "/world/plans/corridor")
    assert len(plans["recording"]) == summary.plans
    strips = _rerun_columns(out, "/eval/garage/learned", index=None)["/eval/garage/learned:LineStrips3D:strips"][0]
    np.testing.assert_allclose(np.asarray(strips[0]), path[:, 1:4])


def test_rerun_command_line(workspace: Path, tmp_path: Path) -> None:
    runner = CliRunner()
    r = runner.invoke(main, ["export-rerun", "-w", str(workspace), "-o", str(tmp_path / "x.mcap")])
    assert r.exit_code == 1 and "ending in .rrd" in r.output
    r = runner.invoke(main, ["export-rerun", "-w", str(workspace), "-o", str(tmp_path / "x.rrd")])
    assert r.exit_code == 0 and "24 frames" in r.output and (tmp_path / "x.rrd").stat().st_size > 0, r.output


def test_missing_layers_are_noted_and_the_rest_is_written(workspace: Path, tmp_path: Path) -> None:
    import shutil

    ws = tmp_path / "ws"
    shutil.copytree(workspace, ws, ignore=shutil.ignore_patterns("map.zarr", "cloud.ply"))
    for command, out in (("export-foxglove", "a.mcap"), ("export-rerun", "a.rrd")):
        r = CliRunner().invoke(main, [command, "-w", str(ws), "-o", str(tmp_path / out)])
        assert r.exit_code == 0 and "mapkit esdf -w" in r.output and "mapkit fuse -w" in r.output, r.output
    assert "/map/esdf" not in _read(tmp_path / "a.mcap") and len(_read(tmp_path / "a.mcap")["/tf"]) == 24
