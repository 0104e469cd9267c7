"""Ingestion against recordings written by third-party writers (rosbags, mcap) with known truth."""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pytest
import zarr
from recordings import T0, T_BODY_CAMERA, K, rotation_angle, write_recording
from rosbags.rosbag2 import StoragePlugin, Writer
from rosbags.typesys import Stores, get_typestore

from mapkit.ingest import IngestConfig, IngestError, ingest, open_frames, open_frames_store


def assert_matches(frames, rec, *, depth_tol: float = 1e-6) -> None:
    assert len(frames) == len(rec.stamps_ns)
    for f, s, T_wc, T_wb, d in zip(frames, rec.stamps_ns, rec.T_world_camera, rec.T_world_body, rec.depth, strict=True):
        assert f.stamp_ns == s
        assert np.abs(f.T_world_camera[:3, 3] - T_wc[:3, 3]).max() < 1e-6
        assert rotation_angle(f.T_world_camera[:3, :3].T @ T_wc[:3, :3]) < 1e-6
        assert np.abs(f.T_world_body - T_wb).max() < 1e-6
        assert f.depth.dtype == np.float32
        np.testing.assert_array_equal(np.isnan(f.depth), np.isnan(d))
        assert np.nanmax(np.abs(f.depth - d)) <= depth_tol
        np.testing.assert_allclose(f.K, K)


@pytest.mark.parametrize("fmt", ["mcap", "ros2", "ros1"])
@pytest.mark.parametrize("pose", ["odometry", "tf", "pose_stamped", "pose_cov"])
def test_formats_and_pose_sources_recover_truth(tmp_path: Path, fmt: str, pose: str) -> None:
    rec = write_recording(tmp_path / "rec", fmt, pose=pose)
    stream = open_frames([rec.path])
    assert_matches(list(stream), rec)
    assert stream.plans[0].body_frame == "base_link"
    assert stream.plans[0].camera_frame == "camera_depth_optical_frame"


def test_bare_db3_file_and_ros2_mcap_directory(tmp_path: Path) -> None:
    rec = write_recording(tmp_path / "rec", "ros2")
    db3 = next(rec.path.glob("*.db3"))
    bare = tmp_path / "bare.db3"
    shutil.copy(db3, bare)
    assert_matches(list(open_frames([bare])), rec)

    # A rosbag2 directory with mcap storage, written by rosbags' own Writer.
    mc = write_recording(tmp_path / "m", "mcap")
    from mapkit.ingest import Source

    store = get_typestore(Stores.ROS2_HUMBLE)
    out = tmp_path / "ros2_mcap"
    with Source(mc.path) as src, Writer(out, version=9, storage_plugin=StoragePlugin.MCAP) as w:
        conns = {}
        for raw in src.messages(list(src.summary.topics)):
            if raw.topic not in conns:
                conns[raw.topic] = w.add_connection(raw.topic, raw.msgtype, typestore=store)
            w.write(conns[raw.topic], raw.log_time_ns, bytes(raw.data))
    assert_matches(list(open_frames([out])), mc)


@pytest.mark.parametrize(
    "kwargs,tol",
    [
        (dict(encoding="mono16"), 1e-6),
        (dict(encoding="32FC1"), 0.0),
        (dict(encoding="16UC1", row_padding=6), 1e-6),
        (dict(encoding="16UC1", big_endian=True), 1e-6),
        (dict(encoding="32FC1", big_endian=True, row_padding=8), 0.0),
        (dict(encoding="16UC1", compressed=True), 1e-6),
        (dict(encoding="32FC1", compressed=True), 2e-3),  # quantised inverse depth
    ],
)
def test_depth_encodings(tmp_path: Path, kwargs: dict, tol: float) -> None:
    rec = write_recording(tmp_path / "rec", "mcap", n=4, **kwargs)
    assert_matches(list(open_frames([rec.path])), rec, depth_tol=tol)


def test_32fc1_invalid_values_become_nan_and_empty_frames_are_dropped(tmp_path: Path) -> None:
    def depth_fn(i: int) -> np.ndarray:
        d = np.full((48, 64), 2.5, np.float32)
        d[0, :4] = [np.inf, -np.inf, 0.0, -1.0]
        d[1, 0] = np.nan
        if i == 2:
            d[:] = np.nan  # a frame with no valid pixel
        return d

    rec = write_recording(tmp_path / "rec", "ros1", n=4, encoding="32FC1", depth_fn=depth_fn)
    stream = open_frames([rec.path])
    frames = list(stream)
    assert len(frames) == 3 and stream.dropped == {"no_valid_depth": 1}
    d = frames[0].depth
    assert np.isnan(d[0, :4]).all() and np.isnan(d[1, 0]) and np.nanmin(d) == np.float32(2.5)


def test_interpolation_gap_and_coverage(tmp_path: Path) -> None:
    # Poses at 120/16 = 7.5 Hz: gaps of 0.133 s exceed the default 0.1 s.
    rec = write_recording(tmp_path / "sparse", "mcap", n=12, pose_stride=16)
    stream = open_frames([rec.path])
    frames = list(stream)
    assert stream.dropped.get("pose_gap", 0) > 0 and len(frames) + stream.dropped["pose_gap"] == 12
    stream = open_frames([rec.path], IngestConfig(max_pose_gap=0.2))
    frames = list(stream)
    assert len(frames) == 12
    # Between samples: linear translation / slerp of the bracketing samples, close to truth.
    err = max(np.abs(f.T_world_body[:3, 3] - T[:3, 3]).max() for f, T in zip(frames, rec.T_world_body, strict=False))
    assert 0 < err < 0.01

    late = write_recording(tmp_path / "late", "mcap", n=12, pose_offset_s=0.2)
    stream = open_frames([late.path])
    frames = list(stream)
    assert stream.dropped["outside_pose_coverage"] == 5 and len(frames) == 7


def test_extrinsic_override_and_intrinsics_option(tmp_path: Path) -> None:
    rec = write_recording(tmp_path / "rec", "mcap", n=3, tf_static=False, camera_info=False)
    with pytest.raises(IngestError, match="--intrinsics"):
        open_frames([rec.path])
    config = IngestConfig(intrinsics=K.copy())
    with pytest.raises(IngestError, match=r"ingest\.extrinsic"):
        open_frames([rec.path], config)
    config.extrinsic = T_BODY_CAMERA.copy()
    assert_matches(list(open_frames([rec.path], config)), rec)


def test_several_inputs_and_frames_store(tmp_path: Path) -> None:
    a = write_recording(tmp_path / "a", "ros1", n=5)
    b = write_recording(tmp_path / "b", "mcap", n=4)
    summary = ingest([a.path, b.path], tmp_path / "ws", progress=False)
    assert summary.frames == 9
    store = open_frames_store(tmp_path / "ws")
    assert len(store) == 9 and list(store.source_index) == [0] * 5 + [1] * 4
    root = zarr.open_group(tmp_path / "ws" / "frames.zarr", mode="r")
    assert root["depth"].shape == (9, 48, 64) and root["depth"].chunks == (1, 48, 64)
    assert root["depth"].metadata.dimension_names == ("frame", "v", "u")
    assert root.attrs["mapkit_version"] and root.attrs["world_frame"] == "world"
    assert len(root.attrs["sources"]) == 2 and root.attrs["dropped"] == {}
    np.testing.assert_allclose(store.K, K)
    np.testing.assert_allclose(store.T_world_camera[5], b.T_world_camera[0], atol=1e-9)
    np.testing.assert_array_equal(np.isnan(store.depth[6]), np.isnan(b.depth[1]))
    assert store.is_current([a.path, b.path], IngestConfig())
    assert not store.is_current([a.path], IngestConfig())
    assert not store.is_current([a.path, b.path], IngestConfig(stride=2))


def test_failed_ingest_leaves_nothing(tmp_path: Path) -> None:
    rec = write_recording(tmp_path / "rec", "mcap", n=3, pose_offset_s=100.0)
    with pytest.raises(IngestError, match="no pose overlaps the depth stamps"):
        ingest([rec.path], tmp_path / "ws", progress=False)
    assert list((tmp_path / "ws").iterdir()) == []


def test_stride_and_max_frames(tmp_path: Path) -> None:
    rec = write_recording(tmp_path / "rec", "mcap", n=10)
    frames = list(open_frames([rec.path], IngestConfig(stride=3)))
    assert [f.stamp_ns for f in frames] == rec.stamps_ns[::3]
    frames = list(open_frames([rec.path], IngestConfig(max_frames=4)))
    assert len(frames) == 4


def test_truncated_mcap_recovers_messages_before_the_cut(tmp_path: Path) -> None:
    rec = write_recording(tmp_path / "rec", "mcap", n=120)
    data = rec.path.read_bytes()
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(data[: int(len(data) * 0.6)])
    stream = open_frames([cut])
    frames = list(stream)
    assert any("truncated" in w for w in stream.warnings)
    assert 30 < len(frames) < 120
    assert_matches(frames, type(rec)(rec.path, rec.stamps_ns[: len(frames)], rec.T_world_body[: len(frames)],
                                     rec.T_world_camera[: len(frames)], rec.depth[: len(frames)]))


def test_header_stamps_sync_not_log_time(tmp_path: Path) -> None:
    # Poses use the message header stamps; depth at stamps shared with odometry → exact.
    rec = write_recording(tmp_path / "rec", "ros2", n=3)
    frames = list(open_frames([rec.path]))
    assert frames[0].stamp_ns == T0


def test_tf_lookup_gives_a_matrix_or_raises_no_pose_with_the_reason():
    from mapkit.ingest._tf import NO_POSE, POSE_GAP, EdgeSeries, NoPose, TfTree

    series = EdgeSeries("world", "body", "test")
    q = np.array([0.0, 0.0, 0.0, 1.0])
    series.add(0, np.array([0.0, 0.0, 0.0]), q)
    series.add(1_000_000_000, np.array([2.0, 0.0, 0.0]), q)
    tree = TfTree()
    tree.replace_dynamic(series)
    T = tree.lookup("world", "body", 500_000_000, max_gap_ns=2_000_000_000)
    np.testing.assert_allclose(T[:3, 3], [1.0, 0.0, 0.0])
    for stamp, gap, reason in ((500_000_000, 100_000_000, POSE_GAP), (2_000_000_000, 2_000_000_000, NO_POSE)):
        with pytest.raises(NoPose) as info:
            tree.lookup("world", "body", stamp, max_gap_ns=gap)
        assert info.value.reason == reason
